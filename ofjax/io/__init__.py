"""Reading real data into a Scene: WLI instrument files, OM photos, the OpticFusion layout.

`load(path, layout=None, um_per_unit=None, poses=None, pixel_size=None) -> Scene` reads a scene
folder in any layout (io.detect: native bundle, OpticFusion WLI-OM, raw instrument files); the
modules below document each format and convention:
  wli          height maps (surfalize formats, plain npy/npz/tif) and height -> orthographic depth
  datx         Zygo .datx through h5py
  om           photos (8/16 bit, EXIF orientation) and EXIF intrinsics
  opticfusion  the OpticFusion dataset layout (wl/, op/camera.xml, op/align.aln)
  raw          a folder of instrument files (wli/, om/)
"""

from ofjax.io.detect import LAYOUTS, detect_layout, load

__all__ = ["LAYOUTS", "detect_layout", "load"]
