"""Two-step data association: WLI registration + OM structure-from-motion, then scaled alignment.

Public API: `associate(scene, ...) -> Association` (ofjax.associate.pipeline), the CLI
`python -m ofjax.associate SCENE_DIR [--report]`, and `pose_errors` (ofjax.associate.evaluate)
to compare poses with ground truth after fixing the gauge.
"""

from ofjax.associate.evaluate import pose_errors
from ofjax.associate.pipeline import Association, associate

__all__ = ["Association", "associate", "pose_errors"]
