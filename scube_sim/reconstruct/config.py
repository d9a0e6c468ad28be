"""The settings of the measured reconstruction, one section per step: `StereoConfig` (multi-view
stereo, `reconstruct.stereo.mvs`), `FusionConfig` (depth maps into a voxel grid, `fusion`) and
`EvidenceConfig` (the whole route: both, the ground and the surfels, `evidence`), and the labels
the route gives. Pydantic models with no torch, so a profile validates before any network loads.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..config import StrictModel, unique_names
from ..labels import LABEL_IDS

__all__ = ["CHUNK_HEIGHT_SHARE", "EvidenceConfig", "FusionConfig", "GROUND_LABEL", "OTHER_LABEL", "StereoConfig"]

GROUND_LABEL = LABEL_IDS["road"]


OTHER_LABEL = LABEL_IDS["undefined"]


CHUNK_HEIGHT_SHARE = 0.25  # the chunk's z extent, a share of its size (as the worlds' grids)


class StereoConfig(StrictModel):
    """Plane-sweep multi-view stereo settings (`reconstruct.stereo.mvs`, whose module docstring
    numbers the steps named here). Depths in metres; pixels at `scale` unless said otherwise."""

    # steps 1-3: the images, the source views and the sweep
    sources: int = Field(default=4, ge=1, le=64)  # source views per reference: more is steadier and slower
    hypotheses: int = Field(default=128, ge=3, le=4096)  # depth planes, uniform in 1/depth: more is finer, slower
    near_m: float = Field(default=2.0, gt=0)  # the nearest plane: lower to reach closer objects, at coarser steps
    far_m: float = Field(default=90.0, gt=0)  # the farthest plane, beyond which stereo measures nothing
    window: int = Field(default=7, ge=3, le=31)  # the census window (odd): wider for faint texture, blurs depth edges
    scale: float = Field(default=0.5, gt=0, le=1)  # images are swept at this share of their resolution: lower is faster
    min_baseline_m: float = Field(default=0.05, ge=0)  # a source closer to the reference camera gives no parallax
    max_axis_angle_deg: float = Field(default=60.0, gt=0, le=180)  # a source turned further away is not used
    # the source choice's preferred motion per hypothesis step, in pixels of the swept images
    good_step_px: float = Field(default=0.5, gt=0)
    # step 7: the confidence
    agreement_tolerance: int = Field(default=2, ge=0)  # hypotheses between a source's own minimum and the winner
    # peak ratio at which that factor of the confidence reaches 1: lower trusts flatter minima (and chance matches)
    peak_full: float = Field(default=0.6, gt=0)
    # steps 4 and 4b: moving boxed objects
    moved_m: float = Field(default=0.1, gt=0)  # a box whose centre moved more than this between instants moves
    box_margin_m: float = Field(default=0.3, ge=0)  # a moving box's mask grows by this
    # each boxed object that moved, swept again in its own frame (off: its pixels use the
    # reference instant's other cameras only); on where the frames carry boxes of moving actors
    movers: bool = False
    mover_min_px: int = Field(default=64, ge=1)  # objects covering fewer pixels than this are not swept again
    chunk: int = Field(default=8, ge=1, le=256)  # step 3: hypotheses per warp and cost batch: lower to save memory
    # step 7, continued
    lone_credit: float = Field(default=0.5, ge=0, le=1)  # agreement of a pixel only one usable source sees
    lone_peak_full: float = Field(default=0.8, gt=0)  # `peak_full` for such a pixel (no other source can contradict it)
    match_px: float = Field(default=0.25, gt=0)  # sub-pixel precision of a match, for the expected depth error
    # confidence scaled down where the expected relative depth error exceeds this (None: off)
    max_rel_error: float | None = Field(default=0.05, gt=0)
    min_agreement: float = Field(default=0.7, ge=0, le=1)  # confidence 0 below this agreement ...
    # ... or, from `weak_agreement` up (None: off), at most `weak_cap`: an unsure pixel the fusion
    # takes only where other views hit the same voxel (`FusionConfig.weak_confidence`)
    weak_agreement: float | None = Field(default=None, ge=0, le=1)
    weak_cap: float = Field(default=0.45, ge=0, le=1)  # keep below the fusion's `min_confidence`
    # step 5b: semi-global aggregation of the aggregated volume (`sgm.semi_global`): 0 (off), 4 or 8
    # paths; penalties in the cost's units for a one-hypothesis step and for any larger jump
    # between neighbours: a larger `sgm_p2` smooths more and rounds off depth edges
    sgm_paths: Literal[0, 4, 8] = 4
    sgm_p1: float = Field(default=0.03, ge=0)
    sgm_p2: float = Field(default=0.2, ge=0)
    # step 9: gap filling: unsure runs of pixels up to this angle between agreeing confident ones (0: off)
    fill_gap_deg: float = Field(default=0.0, ge=0, le=45)
    fill_tolerance: float = Field(default=0.03, gt=0, le=1)  # relative depth difference of the two ends
    # ... or (None: off) the line through the two ends (in inverse depth), extended this share of the
    # run beyond each end (at least 2 pixels), meets the confident pixels there within
    # `fill_tolerance`: a plane seen obliquely, whose ends' depths differ
    fill_coplanar: float | None = Field(default=None, gt=0, le=4)


class FusionConfig(BaseModel):
    """How depth maps become occupancy (module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # as `config.StrictModel`

    voxel_size: float = Field(default=0.2, ge=0.01, le=10)  # metres
    min_confidence: float = Field(default=0.5, ge=0, le=1)  # pixels below give no evidence ...
    # ... unless at or above `weak_confidence` (None: off): such a pixel carves nothing, and a voxel
    # only such pixels hit is occupied where `weak_views` images hit it (module docstring)
    weak_confidence: float | None = Field(default=None, ge=0, le=1)
    weak_views: int = Field(default=2, ge=1)
    weak_fit_weight: float = Field(default=1.0, ge=0, le=1)  # an unsure point's weight in the surfel fit, times its confidence
    max_depth_m: float = Field(default=80.0, gt=0)  # pixels beyond give no evidence
    hit_logodds: float = Field(default=0.85, gt=0)  # log-odds added by a hit at confidence 1 (p 0.7)
    miss_logodds: float = Field(default=-0.6, lt=0)  # ... by a miss at confidence 1 (p 0.35)
    occupied_logodds: float = Field(default=0.0)  # occupied at or above (a single hit suffices)
    band_voxels: float = Field(default=1.5, ge=0)  # no carving this close before a point (voxels) ...
    band_rel: float = Field(default=0.05, ge=0)  # ... or this share of its depth, the larger
    # every n-th pixel in each direction: depth measured at 1/n of the image's resolution and
    # handed back upsampled (stereo at `StereoConfig.scale` 0.5: n = 2) repeats each measurement
    # over n x n pixels: they add cost and no evidence, and neighbours that share one measurement
    # give no footprint or normal between them
    pixel_stride: int = Field(default=1, ge=1)
    carve_stride: int = Field(default=1, ge=1)  # carve along every n-th of those pixels' rays in each direction
    chunk_rays: int = Field(default=4096, ge=1, le=1 << 20)  # rays per carving batch (memory)
    patch_max_rel: float = Field(default=0.1, gt=0)  # a pixel's step to its neighbour's point longer than this x depth is an edge
    edge_margin_px: int = Field(default=3, ge=0)  # pixels this close to a depth edge give no evidence (half the census window)


class EvidenceConfig(StrictModel):
    """The route's settings (module docstring)."""

    stereo: StereoConfig = Field(default_factory=StereoConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    ground_cell_m: float = Field(default=1.0, ge=0.05, le=100)  # the height field's cells
    ground_band_m: float = Field(default=0.2, gt=0)  # a point this close to the height field is ground ...
    ground_max_slope_deg: float = Field(default=30.0, gt=0, le=90)  # ... if its surface tilts at most this
    ground_confidence: float = Field(default=0.5, ge=0, le=1)  # confidence of ground voxels no camera saw
    # beyond the measured ground the height field's rise over its plane decays with this length
    # (`ground.fit_height_field`; None: carried unchanged to the chunk's edge)
    ground_fill_decay_m: float | None = Field(default=8.0, gt=0, le=10_000)
    fill_ground: bool = True  # ground surfels under the columns no observed ground voxel covers
    # surfels on the frames' boxed objects at T where no camera saw them (a car beside the ego,
    # behind the side cameras; the far side of a car ahead): a car its silhouette, anything else its
    # box's sides and top, labelled by the box, marked unobserved at `ground_confidence`; never in a
    # voxel an observed point holds nor where an image saw through (`box_samples`)
    fill_boxes: bool = False
    gaussians_per_voxel: int = Field(default=4, ge=1, le=16)
    # the instants (offsets from T) whose images are stereo references, each against the others
    # (those the frames lack are skipped): a forward-driving camera saw the objects beside it at T
    # from farther back, less obliquely (module docstring: the trade)
    references: list[int] = Field(default_factory=lambda: [0, -3], min_length=1)
    _references_once = field_validator("references")(classmethod(lambda cls, v: unique_names(v)))
    # the surfels' thickness, a share of the voxel: depth noise spreads a voxel's points across the
    # surface, and at hard opacity a thick surfel is hit early by 3 sigma / sin(incidence) (a
    # grazing ray along the road); the build flattens LiDAR surfels the same way. Thinner gives
    # the road back its range but lets a grazing ray slip between neighbouring surfels (the
    # `evidence` profile takes 0.03, where three references add their depth noise to the road)
    max_normal_share: float = Field(default=0.1, gt=0)
    # an observed ground point within this of the height field is moved onto it, its footprint laid
    # flat (None: left where stereo put it). Stereo scatters the road's points about the surface;
    # the field, a median over 1 m cells, is steadier. A step taller than this (a kerb) keeps its points (`snap_ground`)
    ground_snap_m: float | None = Field(default=None, gt=0, le=1)
    # an observed surfel off the road, its centre more than `min_width_above_m` over the height
    # field, is at least this share of the voxel wide (standard deviation along both tangents;
    # None: as fitted). Stereo is confident at texture edges, so a voxel of a car's door holds
    # points on a few centimetres of it, its surfels as small, and a ray through the rest of the
    # voxel slips between them to what lies behind; a voxel the fusion holds occupied is crossed by
    # its surface. 0.144 = 1 / (2 sqrt 12): each of the 2 x 2 Gaussians of a voxel spans its quarter
    # of the face (`widen_surfels`). Surfels near the ground keep their size: a wall's widened foot
    # meets the rays to the road before it
    min_width_share: float | None = Field(default=None, gt=0, le=1)
    min_width_above_m: float = Field(default=0.3, ge=0, le=100)

    def fusion_at_stereo_scale(self) -> FusionConfig:
        """The fusion settings the route uses: `fusion` with the depth maps' pixel stride (a depth
        map at stereo scale s holds one measurement per 1 / s pixels)."""
        return self.fusion.model_copy(update={"pixel_stride": max(1, round(1.0 / self.stereo.scale))})
