"""A content-addressed on-disk store of numpy arrays, safe under many concurrent readers and writers.

Each entry is one ``.npz`` file named by the hash of its key, written atomically (``nsl_hpc.core.atomic``), so a
reader sees either nothing or a whole file; two writers of the same key write identical content, so the
last rename winning is harmless.
"""

import os
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nsl_hpc.core.atomic import replacing
from nsl_hpc.core.seeding import stable_hash

Arrays = dict[str, np.ndarray]


class ArrayCache:
    """Arrays stored under ``root/<hash[:2]>/<hash>.npz``, keyed by a JSON-serialisable mapping."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def path_for(self, key: Mapping[str, Any]) -> Path:
        digest = stable_hash(dict(key), length=32)
        return self.root / digest[:2] / f"{digest}.npz"

    def get_or_create(self, key: Mapping[str, Any], create: Callable[[], Arrays]) -> Arrays:
        """The arrays stored under ``key``; on a miss (or an unreadable file) ``create()`` them and store."""
        path = self.path_for(key)
        try:
            with np.load(path) as stored:
                return {name: stored[name] for name in stored.files}
        except (FileNotFoundError, zipfile.BadZipFile, ValueError, EOFError, OSError):
            arrays = create()
            with replacing(path) as temporary, temporary.open("wb") as handle:
                np.savez(handle, **arrays)  # type: ignore[arg-type]  # numpy's stub takes ** for allow_pickle
            return arrays
