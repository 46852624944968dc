"""
Synthetic rectified stereo sequences of a textured street with exact ground truth.

The renderer ray-casts a procedural scene into a KITTI-like rectified stereo pair:

* a ground plane with an asphalt road, lane markings, crosswalks, kerbs, sidewalks and grass
  (one periodic texture tile: a city grid cell or a highway section);
* axis-aligned boxes standing on the ground: building blocks with windows, bricks and
  multi-scale grime, lamp posts, noise walls, warehouses, parked vans; and moving vehicles
  (vans, trucks, buses) that drive along the lanes at constant speed;
* a sky with faint clouds at infinity.

Frames and units: camera optical frame (x right, y down, z forward), metres, seconds, pixels.
``world`` is the optical frame of the first left camera (KITTI convention); the ground is the
plane ``y = camera height`` in it. Poses are ``T_world_cam`` (4x4, maps points from the left
camera frame to ``world``). Pixel centres are at integer coordinates (OpenCV convention).

Exactness: every pixel samples the scene along the ray through its centre, so a world point
seen at pixel (u, v) with depth d in the left image is seen at (u - fx * B / d, v) in the right
image and where the poses project it in any other frame (static surfaces only). Textures are
prefiltered (rip-maps chosen from the pixel footprint) so that distant surfaces do not alias;
silhouette edges are point sampled unless ``SequenceSpec.supersample`` is 2 or more. This holds
for an exact rig; ``SequenceSpec``'s ``rig_*`` fields render a rig that departs from the
calibration it hands out (true baseline and focal scaled; the right image warped by the
homography of a residual rotation and right-camera intrinsics error, ``right_homography``),
and its ``gain_*`` and ``vignetting*`` fields add independent per-camera exposure and
vignetting.

Restrictions that keep the renderer fast (a per-column ray cast): the cameras stay level
(yaw and height vary, pitch and roll are zero) and every box is taller than the camera.
"""

from __future__ import annotations

from .camera_path import Trajectory
from .renderer import render_sequence, StereoRenderer, SyntheticSequence
from .scene import Scene
from .spec import (KITTI_BASELINE_M, KITTI_CX_PX, KITTI_CY_PX, KITTI_FOCAL_PX, KITTI_HEIGHT,
                   KITTI_WIDTH, PHOTOMETRIC, PRESETS, RenderedFrame, RIG_ERROR, SCENES,
                   SequenceSpec)

__all__ = ['KITTI_BASELINE_M', 'KITTI_CX_PX', 'KITTI_CY_PX', 'KITTI_FOCAL_PX', 'KITTI_HEIGHT',
           'KITTI_WIDTH', 'PHOTOMETRIC', 'PRESETS', 'render_sequence', 'RenderedFrame',
           'RIG_ERROR', 'Scene', 'SCENES', 'SequenceSpec', 'StereoRenderer', 'SyntheticSequence',
           'Trajectory']
