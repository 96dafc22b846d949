"""Seconds from a `pointfarm render ... --json` command's start to its first preview and its
first final frame line on standard output, and to the first frame of each later preview pass
(the preview redrawn with the nodes stored so far) (BENCHMARKS.md, "Previews and COPC first
frames").

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
        if kind == "preview" and frame["frame"] == 0 and counts[kind] > 1:
            print(
                f"preview redrawn: {seconds:.2f} s ({frame['pointsRendered']} points)",
                flush=True,
            )
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
