"""Mesh files as ofjax writes them: PLY, OBJ or GLB, atomically, a PLY naming its length unit.

The unit goes in a PLY header comment placed after the `format` line: the PLY grammar wants
`format` right after `ply`, and readers that hold to it (RPly, Open3D's) refuse a header where a
comment comes first (Open3D read 0 triangles from such files).
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from ofjax import fileio
from ofjax.errors import UserError

FORMATS = ("ply", "obj", "glb")
PLY_UNITS_COMMENT = b"comment units: micrometres (um)"


def units_comment(units: str) -> bytes:
  return PLY_UNITS_COMMENT if units == "um" else f"comment units: {units}".encode()


def write_mesh(mesh: trimesh.Trimesh, path: Path, units: str = "um") -> Path:
  """Writes `mesh` to `path` (format from the suffix) atomically; returns path."""
  fmt = path.suffix.lstrip(".").lower()
  if fmt not in FORMATS:
    raise UserError(f"{path}: unknown mesh format {fmt!r}; use one of {', '.join(FORMATS)}")
  data = mesh.export(file_type=fmt)
  if isinstance(data, str):
    data = data.encode()
  if fmt == "ply":
    end = data.index(b"\n", data.index(b"\nformat ") + 1) + 1  # after the format line
    data = data[:end] + units_comment(units) + b"\n" + data[end:]
  fileio.write_bytes(path, data)
  return path
