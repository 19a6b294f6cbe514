"""Preprocessing: per-object inputs (poses, sparse depths, masks, each object in its own unit).

Modules:

* :mod:`~osn.preprocess.inputs`: the per-object inputs format (:class:`SceneInputs`,
  ``inputs.json`` + ``inputs.npz``: save, load, check) and the normalisation every writer shares.
* :mod:`~osn.preprocess.oracle`: ``osn oracle``, the inputs from a benchgen dataset's ground truth.
* :mod:`~osn.preprocess.sfm`: COLMAP (pycolmap) reconstruction of one object.
* :mod:`~osn.preprocess.repair`: finding and re-posing frames posed against their own matches.
* :mod:`~osn.preprocess.consistency`: whole reconstructions checked against the masks, their own
  frames and the anchor without ground truth; frames dropped, depths distrusted or objects dropped.
* :mod:`~osn.preprocess.video`: ``osn preprocess``, per-object SfM of a whole video (a folder of
  frames and masks, or a benchgen dataset).
* :mod:`~osn.preprocess.alignment`: SfM against ground truth (accuracy, units, test-view alignment),
  the only preprocessing code that reads ground truth.
"""

from osn.preprocess.alignment import align_to_ground_truth, depth_unit
from osn.preprocess.inputs import (
    IGNORE_ID,
    InputsError,
    ObjectInputs,
    SceneInputs,
    check_inputs,
    denormalise_scales,
    load_inputs,
    normalise_scales,
    object_inputs_from_observations,
    save_inputs,
    scale_range,
    scene_volume,
)
from osn.preprocess.oracle import OracleConfig, oracle_inputs
from osn.preprocess.repair import bundle_adjust, repair_registrations
from osn.preprocess.sift_frames import principal_grey
from osn.preprocess.sfm import (
    ObjectRegistrationError,
    ObjectSfM,
    PreprocessConfig,
    PreprocessReport,
    reconstruct_object,
)
from osn.preprocess.video import intrinsics_from_args, load_video, preprocess_dataset, preprocess_video, report_lines

__all__ = [
    "IGNORE_ID", "InputsError", "ObjectInputs", "ObjectRegistrationError", "ObjectSfM", "OracleConfig", "PreprocessConfig",
    "PreprocessReport", "SceneInputs", "align_to_ground_truth", "bundle_adjust", "check_inputs", "denormalise_scales",
    "depth_unit", "intrinsics_from_args", "load_inputs", "load_video", "normalise_scales", "object_inputs_from_observations",
    "oracle_inputs", "preprocess_dataset", "preprocess_video", "principal_grey", "reconstruct_object", "repair_registrations",
    "report_lines", "save_inputs", "scale_range", "scene_volume",
]
