#!/usr/bin/env python3
"""Render a LAS/LAZ scan on a pointfarm server from a script.

Uploads the file (streamed in chunks), submits a keyframed camera-path job, prints the job's
progress as it renders and downloads the frames into a folder as frame_00000.png, ...

The camera path is read from a JSON or TOML file in the format of `pointfarm render
--camera-path` (`frames`, `interpolation`, `keyframes` of `position`, `target`, optionally `up`
and `fov_y_deg`, in the file's coordinates); without one, the camera flies a quarter circle
around the cloud, framed from the bounds in the file's LAS header.

The gRPC stubs are compiled from the service's proto (proto/pointfarm/v1/pointfarm.proto, or
--proto) with grpcio-tools on first use, into a cache folder.

    python pointfarm_client.py scan.laz --out frames/ --server renderhost:50051 \\
        --token-file client.token --size 1280x720 --frames 48

Exits 0 when every frame was downloaded; otherwise prints one line saying what went wrong
(the gRPC status in words and the server's message) and exits 1.
"""

import argparse
import hashlib
import importlib.metadata
import json
import math
import os
import struct
import sys
import tempfile
import tomllib
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import grpc

# Bytes per upload message: well under gRPC's default 4 MiB message limit.
CHUNK_BYTES = 1 << 20
# The service's vertical field of view, in degrees, where a keyframe gives none.
DEFAULT_FOV_Y_DEG = 50.0
# The proto of the repository this script lives in.
DEFAULT_PROTO = Path(__file__).resolve().parents[2] / "proto/pointfarm/v1/pointfarm.proto"
# Frames of the flyover made when no camera path is given.
DEFAULT_FRAMES = 24
CONNECT_TIMEOUT_S = 10.0
# The authorization header sent with every call, or none.
Metadata = tuple[tuple[str, str], ...]


class ClientError(Exception):
    """A problem this script reports in one line before exiting non-zero."""


@dataclass(frozen=True)
class Bounds:
    """A LAS file's header bounds, in its own coordinates."""

    minimum: tuple[float, float, float]
    maximum: tuple[float, float, float]


def load_stubs(proto: Path) -> tuple[ModuleType, ModuleType]:
    """The messages and service stubs of `proto`, compiled once into a cache folder.

    The folder is named by a digest of the proto and of grpcio-tools' version, so a changed
    proto or a new grpcio-tools compiles anew; a compilation is moved into place whole, so
    scripts started at the same time never import a half-written module.
    """
    from grpc_tools import protoc

    source = proto.read_bytes()
    tools_version = importlib.metadata.version("grpcio-tools").encode()
    digest = hashlib.sha256(source + tools_version).hexdigest()[:16]
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    stubs = cache_home / "pointfarm" / "python-stubs" / digest
    if not stubs.is_dir():
        stubs.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=stubs.parent) as scratch:
            work = Path(scratch) / "stubs"
            work.mkdir()
            (work / "pointfarm.proto").write_bytes(source)
            status = protoc.main(
                [
                    "grpc_tools.protoc",
                    f"--proto_path={work}",
                    f"--python_out={work}",
                    f"--grpc_python_out={work}",
                    str(work / "pointfarm.proto"),
                ]
            )
            if status != 0:
                raise ClientError(f"compiling {proto} failed (grpc_tools.protoc exit {status})")
            (work / "pointfarm.proto").unlink()
            try:
                work.rename(stubs)
            except OSError:
                if not stubs.is_dir():  # Not another script's compilation that won the race.
                    raise
    sys.path.insert(0, str(stubs))
    import pointfarm_pb2
    import pointfarm_pb2_grpc

    return pointfarm_pb2, pointfarm_pb2_grpc


def las_bounds(path: Path) -> Bounds:
    """The bounds in the header of the LAS/LAZ file at `path` (LAS 1.0 to 1.4 alike)."""
    with path.open("rb") as file:
        header = file.read(227)
    if len(header) < 227 or header[:4] != b"LASF":
        raise ClientError(f"{path} is not a LAS/LAZ file (no LASF signature)")
    max_x, min_x, max_y, min_y, max_z, min_z = struct.unpack_from("<6d", header, 179)
    return Bounds((min_x, min_y, min_z), (max_x, max_y, max_z))


def flyover(bounds: Bounds, frames: int) -> dict:
    """A camera path file's content: a quarter circle around the cloud, 30 degrees above the
    horizon, always looking at the centre of its bounds and far enough to see all of it."""
    centre = [(lo + hi) / 2 for lo, hi in zip(bounds.minimum, bounds.maximum, strict=True)]
    radius = math.dist(bounds.minimum, bounds.maximum) / 2 or 1.0
    distance = radius / math.sin(math.radians(DEFAULT_FOV_Y_DEG / 2))
    elevation = math.radians(30.0)
    keyframes = []
    for azimuth_deg in (-60.0, -15.0, 30.0):
        azimuth = math.radians(azimuth_deg)
        offset = (
            distance * math.cos(elevation) * math.cos(azimuth),
            distance * math.cos(elevation) * math.sin(azimuth),
            distance * math.sin(elevation),
        )
        position = [c + o for c, o in zip(centre, offset, strict=True)]
        keyframes.append({"position": position, "target": centre})
    return {"frames": frames, "interpolation": "spline", "keyframes": keyframes}


def read_camera_path(path: Path) -> dict:
    """A camera path file (`.json` or `.toml`), as `pointfarm render --camera-path` reads it."""
    parsers = {".json": json.loads, ".toml": tomllib.loads}
    parse = parsers.get(path.suffix.lower())
    if parse is None:
        raise ClientError(f"--camera-path {path}: give a .json or .toml file")
    try:
        return parse(path.read_text())
    except ValueError as error:
        raise ClientError(f"{path} is not a camera path: {error}") from error


def camera_path_message(pb: ModuleType, path: dict, frames: int | None) -> Any:
    """The API's `CameraPath` of a camera path file's content; `frames` replaces its count."""
    interpolations = {"linear": pb.INTERPOLATION_LINEAR, "spline": pb.INTERPOLATION_SPLINE}
    try:
        keyframes = [
            pb.Keyframe(
                position=pb.Vec3(x=k["position"][0], y=k["position"][1], z=k["position"][2]),
                target=pb.Vec3(x=k["target"][0], y=k["target"][1], z=k["target"][2]),
                up=pb.Vec3(x=k["up"][0], y=k["up"][1], z=k["up"][2]) if "up" in k else None,
                fov_y_deg=k.get("fov_y_deg", DEFAULT_FOV_Y_DEG),
            )
            for k in path["keyframes"]
        ]
        keyframe_path = pb.KeyframePath(
            keyframes=keyframes,
            frames=frames if frames is not None else path["frames"],
            interpolation=interpolations[path.get("interpolation", "spline")],
        )
    except (KeyError, IndexError, TypeError, ValueError) as error:
        raise ClientError(f"the camera path is not valid: {error!r}") from error
    return pb.CameraPath(keyframes=keyframe_path)


def file_sha256(path: Path) -> tuple[str, int]:
    """The hex SHA-256 and the size of the file at `path`, read in chunks."""
    digest = hashlib.sha256()
    size = 0
    with path.open("rb") as file:
        while chunk := file.read(CHUNK_BYTES):
            digest.update(chunk)
            size += len(chunk)
    return digest.hexdigest(), size


def upload_messages(pb: ModuleType, path: Path, sha256: str, size: int) -> Iterator[Any]:
    """UploadDataset's stream: the header (name, size, hash), then the bytes chunk by chunk."""
    yield pb.UploadDatasetRequest(
        header=pb.UploadHeader(name=path.name, size_bytes=size, sha256=sha256)
    )
    with path.open("rb") as file:
        while chunk := file.read(CHUNK_BYTES):
            yield pb.UploadDatasetRequest(data=chunk)


def read_token(token: str | None, token_file: Path | None) -> str | None:
    """The bearer token from --token (POINTFARM_TOKEN) or --token-file (POINTFARM_TOKEN_FILE)."""
    if token is not None and token_file is not None:
        raise ClientError("--token and --token-file are both given: give the token once")
    if token_file is not None:
        token = token_file.read_text().rstrip("\r\n")
    if token is not None and (not token or not all(33 <= ord(c) <= 126 for c in token)):
        raise ClientError("the token must be printable ASCII without spaces")
    return token


def open_channel(server: str, tls_ca: Path | None) -> grpc.Channel:
    """A channel to `server`: `https://` is TLS, `http://` plaintext, a bare HOST:PORT
    plaintext unless --tls-ca is given (TLS trusting that CA)."""
    if server.startswith("http://"):
        if tls_ca is not None:
            raise ClientError(f"--tls-ca is for https:// servers, but '{server}' is plaintext")
        return grpc.insecure_channel(server.removeprefix("http://"))
    if not server.startswith("https://") and tls_ca is None:
        return grpc.insecure_channel(server)
    roots = tls_ca.read_bytes() if tls_ca is not None else None
    credentials = grpc.ssl_channel_credentials(root_certificates=roots)
    return grpc.secure_channel(server.removeprefix("https://"), credentials)


def status_line(error: grpc.RpcError) -> str:
    """A failed call as one line: the status code in words, then the server's message."""
    code = error.code()
    words = code.name.lower().replace("_", " ") if code is not None else "error"
    return f"{words}: {error.details()}"


def state_name(pb: ModuleType, state: int) -> str:
    """A job state as the CLI prints it: `running`, `succeeded`, ..."""
    return pb.JobState.Name(state).removeprefix("JOB_STATE_").lower()


def follow(pb: ModuleType, jobs: Any, job: Any, metadata: Metadata) -> Any:
    """Prints the job's progress from WatchJob until it ends; returns the finished job."""
    for event in jobs.WatchJob(pb.WatchJobRequest(id=job.id), metadata=metadata):
        job = event.job
        if event.HasField("frame"):
            total_ms = sum(t.ms for t in event.frame.timings)
            detail = f"frame {event.frame.index} in {total_ms:.0f} ms"
        else:
            detail = state_name(pb, job.state)
        print(f"{job.frames_done}/{job.frames_total} frames  {detail}", flush=True)
    return job


def fetch_frames(pb: ModuleType, jobs: Any, job_id: str, out: Path, metadata: Metadata) -> int:
    """Writes the job's frames from FetchFrames into `out`; returns how many."""
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    png = bytearray()
    for chunk in jobs.FetchFrames(pb.FetchFramesRequest(job_id=job_id), metadata=metadata):
        png += chunk.png
        if chunk.last:
            (out / f"frame_{chunk.index:05}.png").write_bytes(png)
            png.clear()
            written += 1
    return written


def render(args: argparse.Namespace) -> None:
    """Uploads, submits, follows and downloads; raises on any failure."""
    pb, pb_grpc = load_stubs(args.proto)
    width, height = args.size
    token = read_token(args.token, args.token_file)
    metadata: Metadata = (("authorization", f"Bearer {token}"),) if token is not None else ()
    if args.camera_path is not None:
        path = read_camera_path(args.camera_path)
    else:
        path = flyover(las_bounds(args.file), DEFAULT_FRAMES)
    camera_path = camera_path_message(pb, path, args.frames)
    sha256, size = file_sha256(args.file)

    with open_channel(args.server, args.tls_ca) as channel:
        try:
            grpc.channel_ready_future(channel).result(timeout=CONNECT_TIMEOUT_S)
        except grpc.FutureTimeoutError as error:
            raise ClientError(f"cannot connect to {args.server}") from error
        datasets = pb_grpc.DatasetServiceStub(channel)
        jobs = pb_grpc.JobServiceStub(channel)

        messages = upload_messages(pb, args.file, sha256, size)
        dataset = datasets.UploadDataset(messages, metadata=metadata)
        print(f"dataset {dataset.id}: {args.file.name}, {dataset.size_bytes} bytes", flush=True)

        request = pb.SubmitJobRequest(
            request_id=str(uuid.uuid4()),
            dataset_id=dataset.id,
            camera_path=camera_path,
            width=width,
            height=height,
        )
        job = jobs.SubmitJob(request, metadata=metadata)
        print(f"job {job.id}: {job.frames_total} frames of {width}x{height}", flush=True)

        job = follow(pb, jobs, job, metadata)
        if job.state != pb.JOB_STATE_SUCCEEDED:
            reason = job.error or "no reason given"
            raise ClientError(f"job {job.id} {state_name(pb, job.state)}: {reason}")
        written = fetch_frames(pb, jobs, job.id, args.out, metadata)
        if written != job.frames_total:
            raise ClientError(f"fetched {written} of the job's {job.frames_total} frames")
        print(f"{written} frames in {args.out}", flush=True)


def image_size(text: str) -> tuple[int, int]:
    """WIDTHxHEIGHT, for argparse."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"'{text}' is not WIDTHxHEIGHT") from error
    return width, height


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Tokens and the server can also come from POINTFARM_SERVER, POINTFARM_TOKEN, "
        "POINTFARM_TOKEN_FILE and POINTFARM_TLS_CA, as for the pointfarm CLI.",
    )
    env = os.environ.get
    parser.add_argument("file", type=Path, help="the LAS/LAZ file to render")
    parser.add_argument("--out", type=Path, required=True, help="folder for the frames")
    parser.add_argument(
        "--server",
        default=env("POINTFARM_SERVER", "localhost:50051"),
        help="HOST:PORT, http://HOST:PORT or https://HOST:PORT (default: %(default)s)",
    )
    parser.add_argument("--token", default=env("POINTFARM_TOKEN"), help="the client token")
    parser.add_argument(
        "--token-file",
        type=Path,
        default=env("POINTFARM_TOKEN_FILE"),
        help="read the client token from this file instead",
    )
    parser.add_argument(
        "--tls-ca",
        type=Path,
        default=env("POINTFARM_TLS_CA"),
        help="trust the CA certificates in this PEM file (a bare HOST:PORT then means TLS)",
    )
    parser.add_argument(
        "--camera-path",
        type=Path,
        help="keyframes as JSON or TOML, as for `pointfarm render --camera-path` "
        "(default: a quarter circle around the cloud)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        help=f"frames to render (default: the camera path's, or {DEFAULT_FRAMES})",
    )
    parser.add_argument(
        "--size",
        type=image_size,
        default=(1280, 720),
        help="frame size, WIDTHxHEIGHT (default: 1280x720)",
    )
    parser.add_argument(
        "--proto",
        type=Path,
        default=DEFAULT_PROTO,
        help="the service's pointfarm.proto (default: the one of this repository)",
    )
    return parser.parse_args(argv)


def main() -> int:
    args = parse_args()
    try:
        render(args)
    except grpc.RpcError as error:
        print(f"pointfarm_client: {status_line(error)}", file=sys.stderr)
        return 1
    except ClientError as error:
        print(f"pointfarm_client: {error}", file=sys.stderr)
        return 1
    except OSError as error:
        print(f"pointfarm_client: {error.filename}: {error.strerror}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
