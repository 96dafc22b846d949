"""Reads a COPC file with laspy's COPC reader (an implementation independent of pointfarm's
Rust crates) and prints what the export tests compare, as one JSON object: the header's
counts, bounds, scale and offset; the info VLR's cube; the hierarchy's nodes; every point
queried, summed and its extremes in sorted order; the extra dimensions, and the range of
pointfarm's weight where the file has it."""

import json
import sys

import laspy
import numpy as np


def main(path):
    with laspy.CopcReader.open(path) as reader:
        header = reader.header
        info = reader.copc_info
        points = reader.query()
        xyz = np.stack(
            [np.asarray(points.X), np.asarray(points.Y), np.asarray(points.Z)], axis=1
        ).astype(np.int64)
        order = np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))
        ordered = xyz[order]
        entries = list(reader.root_page.entries.values())
        extra = list(header.point_format.extra_dimension_names)
        weights = (
            np.asarray(points["pointfarm_weight"]) if "pointfarm_weight" in extra else None
        )
        print(
            json.dumps(
                {
                    "version": f"{header.version.major}.{header.version.minor}",
                    "pointFormat": header.point_format.id,
                    "headerPoints": int(header.point_count),
                    "queried": int(len(points)),
                    "mins": [float(v) for v in header.mins],
                    "maxs": [float(v) for v in header.maxs],
                    "scales": [float(v) for v in header.scales],
                    "offsets": [float(v) for v in header.offsets],
                    "center": [float(v) for v in info.center],
                    "halfsize": float(info.halfsize),
                    "nodes": len(entries),
                    "entryPoints": int(sum(e.point_count for e in entries if e.point_count > 0)),
                    "sum": [int(v) for v in xyz.sum(axis=0)],
                    "first": ordered[:3].tolist(),
                    "last": ordered[-3:].tolist(),
                    "extraDimensions": extra,
                    "weightRange": None
                    if weights is None
                    else [int(weights.min()), int(weights.max())],
                }
            )
        )


if __name__ == "__main__":
    main(sys.argv[1])
