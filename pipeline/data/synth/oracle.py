"""The oracle light of an insertion or edit case: Mitsuba's exact incident radiance for each sample ray.

For a shading point p and direction wi that the render layer draws, the oracle path traces the ray
p + t wi in the room with the case applied (the object present, or the material edited), so the light it
returns includes everything the view's own render includes. Re-rendering a case under it checks the
evaluation itself: what differs from the Mitsuba render of the case is Monte Carlo noise and the BRDF
models (Mitsuba's principled diffuse lobe is Burley's, ours Lambert's; its specular shadowing is
separable Smith, ours height-correlated).
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.cases import InsertedObject, MaterialEdit, room_with_edit, room_with_object
from pipeline.data.synth.scene import Camera, Room


class MitsubaOracle:
    """Radiance callbacks (`models.render_layer.PointRadianceFn`, view space) for the cases of one view.
    spp: path samples per sample ray; seed: the first of the seeds its calls draw (each call its own)."""

    def __init__(self, room: Room, camera: Camera, max_depth: int, spp: int, seed: int):
        self.room, self.max_depth, self.spp, self.seed = room, int(max_depth), int(spp), int(seed)
        w2v = mb.world_from_view(camera)
        self.rot, self.origin = w2v[:3, :3], w2v[:3, 3]
        self.calls = 0

    def for_object(self, obj: InsertedObject):
        return self._callback(mb.load_scene(room_with_object(self.room, obj), self.max_depth))

    def for_edit(self, edit: MaterialEdit):
        return self._callback(mb.load_scene(room_with_edit(self.room, edit), self.max_depth))

    def _callback(self, scene):
        def radiance(idx, origin, wi, image):
            o = origin.detach().double().cpu().numpy() @ self.rot.T + self.origin
            d = wi.detach().double().cpu().numpy() @ self.rot.T
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            self.calls += 1
            mean, _ = mb.radiance(scene, o, d, self.spp, seed=self.seed + self.calls)
            return torch.from_numpy(mean).to(origin.dtype).to(origin.device)

        return radiance
