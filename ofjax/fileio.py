"""Atomic file writing: every file ofjax writes for the user goes to a temporary name, then is renamed.

An interrupted write therefore leaves either the previous file or the new one, never half of one.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
  """Yields a temporary path beside `path`; on success it is renamed onto `path`.

  `suffix` defaults to the target's suffix so that writers which pick a format by extension
  (PIL, trimesh, open3d) still see the right one.
  """
  path = Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp",
                             dir=path.parent)
  os.close(fd)
  # mkstemp creates 0600; the user's files get the usual permissions (0666 less the umask).
  umask = os.umask(0)
  os.umask(umask)
  os.chmod(tmp, 0o666 & ~umask)
  tmp = Path(tmp)
  try:
    yield tmp
    os.replace(tmp, path)
  finally:
    if tmp.exists():
      tmp.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
  with atomic_path(path) as tmp:
    tmp.write_text(text)


def write_json(path: str | os.PathLike, obj: Any) -> None:
  write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  with atomic_path(path) as tmp:
    tmp.write_bytes(data)


def write_npz(path: str | os.PathLike, **arrays: Any) -> None:
  """Like numpy.savez_compressed, but byte-reproducible: zip entries carry a fixed timestamp."""
  import zipfile

  import numpy as np
  from numpy.lib import format as npy_format
  with atomic_path(path) as tmp:
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
      for key, value in arrays.items():
        info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
        info.compress_type = zipfile.ZIP_DEFLATED
        with zf.open(info, "w", force_zip64=True) as fh:
          npy_format.write_array(fh, np.asanyarray(value), allow_pickle=False)
