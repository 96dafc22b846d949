"""Seconds from a `pointfarm render ... --json` command's start to its first preview and its
first final frame line on standard output (BENCHMARKS.md, "Time to the first preview frame").

    python3 bench/first_frame.py pointfarm render campaign/ --preview --out x.png --json
"""

import json
import subprocess
import sys
import time


def main() -> int:
    started = time.monotonic()
    proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.PIPE, text=True)
    counts = {"preview": 0, "final": 0}
    for line in proc.stdout:
        seconds = time.monotonic() - started
        frame = json.loads(line)
        kind = "preview" if frame.get("preview") else "final"
        counts[kind] += 1
        if counts[kind] == 1:
            print(
                f"first {kind} frame: {seconds:.2f} s "
                f"({frame['pointsRendered']} of {frame['pointsTotal']} points)",
                flush=True,
            )
    proc.wait()
    print(f"done: {time.monotonic() - started:.2f} s, exit {proc.returncode}, frames {counts}")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
