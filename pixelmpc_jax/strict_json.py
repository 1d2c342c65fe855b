"""How the project writes files: atomically (:func:`write_atomic`: never a half-written file), and JSON
strict: no NaN or Infinity (which ``json`` writes by default and strict parsers reject), numpy values as
Python ones.

A non-finite number becomes ``null``: a missing figure, not a number that is not one. Every writer of the
package (JSON results, dataset laps, DOF checkpoints) goes through :func:`write_atomic`.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np


def json_safe(value):
    """Non-finite floats -> None, numpy scalars and arrays -> Python, dict keys -> str, recursively."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps(data, **kwargs) -> str:
    """``json.dumps`` of :func:`json_safe` of ``data``, strict (``allow_nan=False``)."""
    return json.dumps(json_safe(data), allow_nan=False, **kwargs)


def write_atomic(path, write: Callable[[BinaryIO], object]) -> None:
    """Write a file atomically: ``write(f)`` fills a temporary file in the same directory (``f`` is open for
    binary writing), which is flushed to disk and moved onto ``path`` by ``os.replace``; on any error it is
    removed and ``path`` is left as it was. The file is readable by all (0644)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json_atomic(path, data, indent: int | None = 2, default=None) -> None:
    """Write ``data`` as strict JSON (:func:`json_safe`, ``allow_nan=False``) to ``path``, atomically
    (:func:`write_atomic`). ``default``: as ``json.dump``'s, for objects JSON has no form for."""
    text = json.dumps(json_safe(data), indent=indent, default=default, allow_nan=False)
    write_atomic(path, lambda f: f.write(text.encode()))
