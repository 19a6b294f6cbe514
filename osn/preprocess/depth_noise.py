"""Whether a scene's sparse depths are exact or noisy, measured on the inputs alone.

Three training options correct for inputs whose poses and depths are a few per cent off (SfM's):
the robust sparse-depth loss (``depth_robust``), the silhouette-depth term (``w_edge``) and
objects' grids a voxel per pixel (``field.object_resolution``). On exact inputs each of them
lowers the valid set's IoU. Their ``auto`` picks by a property any inputs can be measured for,
never by where the inputs came from: per object, the share of its depth-against-frame tests in
which a sparse depth lies in front of what another frame observed there
(:func:`osn.preprocess.freespace.contradicted_share`). Exact depths contradict one another only
where a block of pixels straddles a depth edge; SfM's also where a pose is a few degrees off or
a point is a phantom the preprocess's vote kept. Inputs are *noisy* when their worst object's
share exceeds :data:`NOISY_SHARE` (measurements in docs/experiments/).

Pure numpy on :class:`~osn.preprocess.inputs.SceneInputs`; nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

from osn.preprocess.freespace import MARGIN, contradicted_share, occlusion_tests
from osn.preprocess.inputs import SceneInputs

#: Inputs whose worst object contradicts itself in more than this share of its tests are noisy.
NOISY_SHARE = 0.006


@dataclass(frozen=True)
class DepthConsistency:
    """Each object's contradicted share (in the order of ``inputs.objects``), the worst of them,
    and whether that makes the inputs noisy."""

    shares: tuple[float, ...]
    worst: float
    noisy: bool

    def record(self) -> dict:
        """Plain data for a run's records."""
        return {"contradicted_shares": list(self.shares), "worst": self.worst, "noisy": self.noisy,
                "threshold": NOISY_SHARE}


def depth_consistency(inputs: SceneInputs) -> DepthConsistency:
    """Measure every object's :func:`~osn.preprocess.freespace.contradicted_share` in its own
    frame and unit; noisy when the worst exceeds :data:`NOISY_SHARE`."""
    K, W, H = inputs.K, inputs.width, inputs.height
    shares = tuple(contradicted_share(occlusion_tests(o.cam_to_obj, o.sparse_pix, o.sparse_depth, K, W, H, MARGIN))
                   for o in inputs.objects)
    worst = max(shares, default=0.0)
    return DepthConsistency(shares, worst, worst > NOISY_SHARE)
