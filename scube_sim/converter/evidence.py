"""The evidence route: measured geometry (`scube_sim.reconstruct`: stereo, fusion, surfels, the
ground), then, where the profile names one, the learned completion of what no camera saw
(`model.completion`) merged with it (`merge`). The scene is in the chunk frame (x forward, y left,
z up from the road under the ego, metres) and traces at hard opacity.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from ..camera.frames import Frames, chunk_to_world, ego_poses_in_chunk
from ..errors import InputError
from ..memory import peak_mb, reset_peak
from ..model.checkpoint import load_model, resolve_checkpoint
from ..model.completion.features import completion_input
from ..model.completion.net import CompletionNet
from ..reconstruct.evidence import Evidence, measure_evidence
from ..reconstruct.surfels import scene_from_evidence
from ..transforms import invert_pose
from .conversion import Conversion, checkpoint_hashes, context_metadata, one_torch_thread
from .merge import CompletionGrid, merge_completion
from .profile import ConverterProfile

__all__ = ["EvidencePipeline"]


class EvidencePipeline:
    """The evidence route of a profile (route `evidence`): the completion network, if any, loaded once."""

    OPTIONS = ("evidence",)

    def __init__(self, profile: ConverterProfile):
        self.profile = p = profile
        self.paths: dict = {}
        self.completion = None
        if p.completion is not None:
            self.paths["completion"] = resolve_checkpoint(p.completion.checkpoint)
            self.completion, run = load_model("completion", self.paths["completion"])
            if not isinstance(self.completion, CompletionNet):
                raise InputError(f"{self.paths['completion']}: not a completion checkpoint")
            self.completion_voxel_size = float(run.data.get("voxel_size", 0.8))

    @torch.no_grad()
    def convert(self, frames: Frames, *, seed: int = 0, max_range: float | None = None,
                evidence: Evidence | None = None, status: Callable[[str], None] | None = None) -> Conversion:
        """Frames -> the scene (chunk frame): the measured evidence's surfels, completed where the
        profile names a completion; `seed` is not used (the route draws nothing), max_range: keep
        only the voxels whose centre lies within this many metres (horizontally) of the ego.
        evidence: these frames' `Evidence`, measured with this profile's settings
        (`reconstruct.evidence.measure_evidence`), used instead of measuring it again (several
        completions compared on one measurement; stereo_s is then 0). status: called with one line
        as each stage (each stereo image, the fusion, the completion) starts. Timings: stereo_s,
        fusion_s (fusion, ground and surfels) and completion_s. Same frames, same bytes."""
        ev = evidence
        reset_peak()
        t0 = time.perf_counter()
        parts: dict[str, float] = {"stereo_s": 0.0}
        cfg = self.profile.evidence
        if ev is None:
            ev = measure_evidence(frames, invert_pose(chunk_to_world(frames)), cfg, timings=parts, status=status)
        scene = scene_from_evidence(ev, cfg)
        scene.metadata.update({"cameras": list(frames.names), "timestamp": float(frames.timestamp)})
        t1 = time.perf_counter()
        parts["fusion_s"] = t1 - t0 - parts["stereo_s"]
        completed = uncompleted = grid = None
        if self.completion is not None:
            if status:
                status("completion: the network on the evidence, then the merge")
            uncompleted = scene
            feats = completion_input(ev, self.completion_voxel_size, min_confidence=cfg.fusion.min_confidence,
                                     pixel_stride=cfg.fusion_at_stereo_scale().pixel_stride, max_depth_m=cfg.fusion.max_depth_m)
            sub = None
            with one_torch_thread():
                occ_logit, lab_logit, sub_logit = self.completion.forward_with_subcells(torch.from_numpy(feats)[None])
                if sub_logit is not None:
                    sub = torch.sigmoid(sub_logit[0]).double().numpy()
            occ = torch.sigmoid(occ_logit[0]).double().numpy()
            lab = lab_logit[0].argmax(0).numpy()
            grid = CompletionGrid(occ, lab, feats, np.asarray(ev.corner, np.float64), self.completion_voxel_size)
            scene, completed = merge_completion(scene, grid, self.profile.completion,
                                                ego_poses=ego_poses_in_chunk(frames), subcells=sub, boxes=ev.boxes)
            parts["completion_s"] = time.perf_counter() - t1
        if max_range is not None:
            centres = scene.origin[:2] + (scene.ijk[:, :2] + 0.5) * scene.voxel_size
            scene = scene.select_voxels(np.linalg.norm(centres, axis=1) <= max_range)
        timings = {**parts, "peak_mb": peak_mb()}
        scene.metadata.update({
            "source": "scube_sim.convert",
            "profile": self.profile.name,
            "route": "evidence",
            "max_range_m": None if max_range is None else float(max_range),
            "frames": {str(key): str(v) for key, v in frames.metadata.items()},
            "evidence": self.profile.evidence.model_dump(mode="json"),
        })
        if completed is not None:
            scene.metadata["completion"] = {**self.profile.completion.model_dump(mode="json"),
                                            "checkpoint_sha256": checkpoint_hashes(self.paths)["completion"],
                                            "voxel_size": self.completion_voxel_size, **completed}
            scene.metadata["confidence_kind"] = ("fused occupancy probability; unobserved ground: a constant; "
                                                 "completed: the network's occupancy probability")
        scene.metadata.update(context_metadata(frames, "all: stereo over every camera of every instant given"))
        return Conversion(scene, timings, uncompleted=uncompleted, completion_grid=grid)


