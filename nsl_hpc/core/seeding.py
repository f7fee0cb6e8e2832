"""Stable hashes and seeds derived from content, independent of process, platform and expansion order."""

import hashlib
import json
from typing import Any


def stable_hash(obj: Any, length: int = 16) -> str:
    """Hex digest (``length`` characters) of a JSON-serialisable object, key order ignored."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def stable_seed(*parts: Any) -> int:
    """A 63-bit seed determined only by ``parts`` (e.g. ``("init", system, seed)``)."""
    return int(stable_hash(list(parts), length=16), 16) >> 1
