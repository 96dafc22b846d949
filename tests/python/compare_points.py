"""Compares every point of a source LAS/LAZ file with a COPC file exported from it, both read
with laspy (an implementation independent of pointfarm's Rust crates), and prints one JSON
object: the points on each side, the dimensions compared, and per dimension the points that
differ once both sides are sorted by every dimension (a point for point comparison that does
not depend on the order the export wrote them in).

Each point is the tuple of every LAS attribute in the extended formats' terms: coordinates as
integers on the source's scale and offset; a legacy scan angle rank (whole degrees) against
the export's scan angle in 0.006 degree units; fields a legacy format lacks (overlap,
scanner channel) and GPS time where the source has none are 0; RGB, near-infrared, the wave
packet and every extra dimension where the source has them."""

import json
import sys

import laspy
import numpy as np

RETURNS = ["return_number", "number_of_returns"]
FLAGS = ["synthetic", "key_point", "withheld", "scan_direction_flag", "edge_of_flight_line"]
PLAIN = ["intensity", "classification", "user_data", "point_source_id"]
WAVE = [
    "wavepacket_index",
    "wavepacket_offset",
    "wavepacket_size",
    "return_point_wave_location",
    "x_t",
    "y_t",
    "z_t",
]


def columns(points, header, scale, offset, source_format, dims, is_source):
    """The compared columns of `points`: name -> 1-D array."""
    names = set(points.point_format.dimension_names)
    out = {}
    for axis, name in enumerate("xyz"):
        out[name.upper()] = np.round(
            (np.asarray(points[name], dtype=np.float64) - offset[axis]) / scale[axis]
        ).astype(np.int64)
    for name in RETURNS + FLAGS + PLAIN:
        out[name] = np.asarray(points[name]).astype(np.int64)
    extended = source_format >= 6
    for name in ["overlap", "scanner_channel"]:
        out[name] = (
            np.asarray(points[name]).astype(np.int64)
            if name in names
            else np.zeros(len(points), dtype=np.int64)
        )
    if is_source and not extended:
        out["scan_angle"] = np.asarray(points["scan_angle_rank"]).astype(np.int64)
    elif not extended:
        raw = np.asarray(points["scan_angle"]).astype(np.float64)
        out["scan_angle"] = np.round(raw * 0.006).astype(np.int64)
    else:
        out["scan_angle"] = np.asarray(points["scan_angle"]).astype(np.int64)
    out["gps_time"] = (
        np.asarray(points["gps_time"]).astype(np.float64)
        if "gps_time" in names
        else np.zeros(len(points))
    )
    for name in dims:
        values = np.asarray(points[name])
        if values.ndim == 1:
            out[name] = values
        else:
            for k in range(values.shape[1]):
                out[f"{name}[{k}]"] = values[:, k]
    return out


def main(source_path, copc_path):
    source = laspy.read(source_path)
    source_format = source.header.point_format.id
    scale = source.header.scales
    offset = source.header.offsets
    names = set(source.point_format.dimension_names)
    dims = [d for d in ["red", "green", "blue", "nir"] + WAVE if d in names]
    extra = list(source.point_format.extra_dimension_names)
    dims += extra
    with laspy.CopcReader.open(copc_path) as reader:
        exported = reader.query()
        exported_format = reader.header.point_format.id
        exported_extra = list(reader.header.point_format.extra_dimension_names)
    left = columns(source.points, source.header, scale, offset, source_format, dims, True)
    right = columns(exported, None, scale, offset, source_format, dims, False)
    compared = list(left.keys())
    mismatched = {}
    if len(source.points) == len(exported):
        # Sorted by every column, last key first in np.lexsort.
        keys = lambda cols: [cols[name] for name in reversed(compared)]
        left_order = np.lexsort(keys(left))
        right_order = np.lexsort(keys(right))
        for name in compared:
            a = left[name][left_order]
            b = right[name][right_order]
            differ = int(np.count_nonzero(a != b))
            if differ:
                mismatched[name] = differ
    print(
        json.dumps(
            {
                "sourcePoints": int(len(source.points)),
                "exportedPoints": int(len(exported)),
                "sourceFormat": int(source_format),
                "exportedFormat": int(exported_format),
                "compared": compared,
                "sourceExtra": extra,
                "exportedExtra": exported_extra,
                "mismatched": mismatched,
            }
        )
    )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
