"""Multi-view geometry without learning: plane-sweep costs (`sweep`), their semi-global
aggregation (`sgm`) and winner-take-all depth and confidence (`winner`), the compiled versions
of the three (`compiled`), the choice of source views (`views`) and multi-view stereo over a
`Frames` (`mvs`).

Frames: OpenCV cameras (x right, y down, z forward); intrinsics are (3, 3) pinhole K in the
project's pixel convention (pixel (u, v) spans [u, u + 1), its centre at u + 0.5:
`camera.Intrinsics.K`); relative poses are (4, 4) rigid transforms; depths are metres along the
reference camera's optical axis (camera z).
"""

from ..config import StereoConfig
from .movers import moved_boxes, moved_pixels
from .mvs import StereoResult, stereo_depth
from .sweep import (
    COSTS,
    census_codes,
    combine_costs,
    cost_ad,
    cost_census,
    cost_hamming,
    cost_ncc,
    grey,
    inverse_depth_hypotheses,
    sweep_cost,
    warp_to_reference,
)
from .views import SourceView, candidates, select_sources
from .winner import winner_take_all

__all__ = ["COSTS", "SourceView", "StereoConfig", "StereoResult", "candidates", "census_codes", "combine_costs",
           "cost_ad", "cost_census", "cost_hamming", "cost_ncc", "grey", "inverse_depth_hypotheses", "moved_boxes",
           "moved_pixels", "select_sources", "stereo_depth", "sweep_cost", "warp_to_reference", "winner_take_all"]
