"""The two-step data association (OpticFusion Sec. 3.2) from a Scene's raw data to posed cameras.

Step 1 registers the WLI scans (ofjax.associate.wli) and reconstructs the OM photos with SfM
(ofjax.associate.sfm); step 2 maps the SfM frame into the WLI um frame with a similarity
(ofjax.associate.align), re-poses the photos on the WLI surface and adjusts photos and SfM points
together with the points held on it (ofjax.associate.ground); when the scans carry intensity
images, the photos' SIFT keypoints matched to theirs anchor each photo on exact WLI points
(ofjax.associate.anchor) and the adjustment holds them there. The result's scene has every
camera's c2w in um (OpenCV axes) in the WLI world frame (scan 0, sample up), and the OM
intrinsics of the SfM camera. Nothing here reads ground truth or writes into the
scene directory; the CLI writes once everything succeeded.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from ofjax import scene as scene_lib
from ofjax.associate import align, anchor, ground, sfm, wli
from ofjax.errors import UserError


@dataclasses.dataclass
class Association:
  scene: scene_lib.Scene  # a copy of the input with every camera posed
  wli: wli.WLIRegistration
  sfm: sfm.SfMResult
  align: align.Alignment
  ground: ground.Grounding
  anchoring: anchor.Anchoring | None  # the photos' anchors on the WLI intensity images, if any
  seconds: dict[str, float]  # wall time of "wli", "sfm", "align" (step 2 with re-posing), "total"


def stage_hint(photos: list[scene_lib.OMImage], c2w_sfm: dict[str, np.ndarray]):
  """[3, 3] the stage priors' estimate of the SfM-to-WLI rotation (align.stage_turn) from the
  registered photos with a tilt/azimuth prior, in the WLI world frame (whose axes are the WLI
  priors' sample frame); None when fewer than two registered photos have one."""
  have = [o for o in photos if o.name in c2w_sfm and o.prior and "tilt_deg" in o.prior]
  if len(have) < 2:
    return None
  return align.stage_turn([c2w_sfm[o.name][:3, :3] for o in have],
                          [wli.prior_rotation(o.prior) for o in have])


def associate(scene: scene_lib.Scene, workdir: str | Path | None = None, min_overlap: float = 0.2,
              min_fitness: float = 0.3, min_registered: float = 1.0, seed: int = 0,
              max_image_size: int = sfm.MAX_IMAGE_SIZE,
              max_num_features: int = sfm.MAX_NUM_FEATURES,
              scene_dir: str = "SCENE_DIR") -> Association:
  """Poses every WLI scan and OM photo of `scene` in um.

  min_overlap: ICP fitness for two scans to count as overlapping. min_fitness: share of SfM points
  that must land on the WLI surface. min_registered: share of OM photos SfM must register (the
  default 1.0 needs all: a photo without a pose cannot be trained on). seed: every random stage's
  (the RANSACs of registration, SfM, alignment, anchors and re-posing, and the SfM mapper): the
  same scene and seed give the same poses. `workdir` keeps pycolmap's files (default: a temporary
  directory, removed afterwards).
  """
  t = {"start": time.perf_counter()}
  reg = wli.register_scans(scene.wli, min_overlap, scene_dir, seed)
  t["wli"] = time.perf_counter()
  if workdir is None:
    with tempfile.TemporaryDirectory(prefix="ofjax-sfm-") as tmp:
      rec = sfm.run_sfm(scene.om, tmp, scene_dir, seed, max_image_size, max_num_features)
  else:
    rec = sfm.run_sfm(scene.om, workdir, scene_dir, seed, max_image_size, max_num_features)
  t["sfm"] = time.perf_counter()
  n = len(scene.om)
  if len(rec.c2w) < max(3, int(np.ceil(min_registered * n))):
    shown = ", ".join(rec.missing[:10]) + (" ..." if len(rec.missing) > 10 else "")
    raise UserError(f"{scene_dir}/om: structure-from-motion registered only {len(rec.c2w)} of {n} "
                    f"photos (unregistered: {shown}); remove those photos from scene.json or "
                    "retake them with more overlap")
  forward = np.array([c[:3, 2] for c in rec.c2w.values()])
  al = align.align_om_to_wli(rec.points, reg.points, reg.normals, reg.voxel_um, forward,
                             min_fitness, scene_dir, turn_hint=stage_hint(scene.om, rec.c2w),
                             seed=seed)
  c2w_um = {name: align.om_c2w_um(c, al.S) for name, c in rec.c2w.items()}
  height, width = scene.om[0].shape
  anchoring = anchor.anchor_photos(scene.wli, reg.c2w, [o for o in scene.om if o.name in c2w_um],
                                   rec.K, seed)
  gr = ground.ground_cameras(c2w_um, rec.points @ al.S[:3, :3].T + al.S[:3, 3], rec.observations,
                             rec.K, (width, height), reg.points, reg.normals, reg.voxel_um,
                             anchoring, seed)
  t["align"] = time.perf_counter()
  wli_scans = [dataclasses.replace(s, c2w=c) for s, c in zip(scene.wli, reg.c2w)]
  om = [dataclasses.replace(o, K=rec.K.copy(), c2w=gr.c2w[o.name])
        if o.name in gr.c2w else dataclasses.replace(o, c2w=None) for o in scene.om]
  posed = dataclasses.replace(scene, wli=wli_scans, om=om)
  seconds = {"wli": t["wli"] - t["start"], "sfm": t["sfm"] - t["wli"],
             "align": t["align"] - t["sfm"], "total": t["align"] - t["start"]}
  return Association(posed, reg, rec, al, gr, anchoring, seconds)
