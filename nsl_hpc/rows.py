"""Task outcome rows: one single-row Parquet file per task, written atomically."""

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from nsl_hpc.atomic import write_parquet


def row_path(out_dir: str | os.PathLike, task_id: str) -> Path:
    """``<out_dir>/rows/<id[:2]>/<id>.parquet``: bucketed so 63k rows do not share one directory."""
    return Path(out_dir) / "rows" / task_id[:2] / f"{task_id}.parquet"


def write_row_atomically(row: Mapping[str, Any], path: Path) -> None:
    """Write ``row`` as a one-row Parquet file: a temporary file in the same directory, then a rename."""
    write_parquet(pa.Table.from_pylist([dict(row)]), path)


def read_row(path: Path) -> dict[str, Any]:
    """The row stored at ``path``."""
    return pq.read_table(path).to_pylist()[0]
