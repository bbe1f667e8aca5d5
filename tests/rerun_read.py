"""A Rerun recording read back with Rerun's own reader, for the tests: (entity path, column) -> values, with
each chunk's `time` (s) under (entity path, "time")."""

from __future__ import annotations


def read_rrd(path) -> dict:
    from rerun.chunk import RrdReader

    columns = {}
    for chunk in RrdReader(path).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith((":scalars", ":translation", ":half_sizes", ":vertex_positions", ":vertex_colors")):
                columns.setdefault((chunk.entity_path, name), []).extend(batch.column(name).to_pylist())
                if "time" in batch.schema.names:  # a duration in ns
                    columns.setdefault((chunk.entity_path, "time"), []).extend(
                        v / 1e9 for v in batch.column("time").cast("int64").to_pylist())
    return columns
