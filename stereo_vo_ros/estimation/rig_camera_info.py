"""
The calibration refined by the rig estimate, as ROS CameraInfo fields and YAML.

The rig error ``theta`` (:data:`.rig_measurement.PARAMETERS`: roll, pitch, yaw in rad about
the right camera's optical z, x, y axes (x right, y down, z forward), focal ratio, disparity
offset in pixels) is folded into the right camera: intrinsics ``K`` (pixels) with the focal
ratio and principal point x, rectification rotation ``R`` turned by the residual rotation;
the projection matrices ``P`` stay the calibrated ones (the right one's ``P[0, 3]`` is
``-f_x B``, pixels times the baseline ``B`` in metres). The YAML is the
camera_calibration_parsers layout, both cameras under ``left``/``right``. Written by
``stereo_vo run --save-calibration``.
"""

from __future__ import annotations

import numpy as np

from .camera import StereoCalibration
from .rig_measurement import rotation_zxy


def refined_camera_infos(calib: StereoCalibration, theta: np.ndarray) -> tuple[dict, dict]:
    """
    Return the CameraInfo fields of both cameras with the rig error folded in.

    The right camera gets intrinsics ``K_err`` (focal ratio, principal point x) and its
    rectification rotation turned by the residual rotation, exactly; the projection matrices
    stay the calibrated ones. Such a pair describes the images as they are, but as
    ``raw`` input (``pipeline.input_kind: raw``; no distortion when the input was rectified):
    a rectified CameraInfo (P only) cannot hold a rotated right camera. The metric scale
    (baseline, common focal length) is the calibration's: the images do not tell it.

    Parameters
    ----------
    calib : StereoCalibration
        The calibration the estimate refers to.
    theta : np.ndarray
        (5,) rig error (``PARAMETERS``).

    Returns
    -------
    tuple of dict
        ``k`` (9), ``d``, ``r`` (9), ``p`` (12), ``width``, ``height``, ``distortion_model``
        for the left and the right camera (lists of floats, row-major).

    """
    theta = np.asarray(theta, np.float64)
    R = rotation_zxy(theta[:3])
    out = []
    for cam, K, rot in ((calib.left, calib.K_left, np.eye(3)),
                        (calib.right, calib.K_right, R)):
        K = np.array(K, np.float64)
        if cam is calib.right:
            K[:2, :2] *= 1.0 + theta[3]
            K[0, 2] -= theta[4]
        R_rect = np.eye(3) if calib.kind == 'rectified' else cam.R
        D = np.zeros(5) if calib.kind == 'rectified' else cam.D
        model = 'plumb_bob' if calib.kind == 'rectified' else cam.distortion_model
        out.append({'width': int(cam.width), 'height': int(cam.height),
                    'distortion_model': model, 'd': [float(v) for v in D],
                    'k': [float(v) for v in K.ravel()],
                    'r': [float(v) for v in (R_rect @ rot).ravel()],
                    'p': [float(v) for v in cam.P.ravel()]})
    return out[0], out[1]


def camera_info_yaml(left: dict, right: dict) -> str:
    """Return both cameras in the camera_calibration_parsers YAML layout, under left/right."""
    def block(name: str, info: dict) -> list[str]:
        def matrix(key: str, rows: int, cols: int, data: list) -> list[str]:
            values = ', '.join(repr(float(v)) for v in data)
            return [f'  {key}:', f'    rows: {rows}', f'    cols: {cols}',
                    f'    data: [{values}]']
        return ([f'{name}:', f'  image_width: {info["width"]}',
                 f'  image_height: {info["height"]}', f'  camera_name: {name}']
                + matrix('camera_matrix', 3, 3, info['k'])
                + [f'  distortion_model: {info["distortion_model"]}']
                + matrix('distortion_coefficients', 1, len(info['d']), info['d'])
                + matrix('rectification_matrix', 3, 3, info['r'])
                + matrix('projection_matrix', 3, 4, info['p']))
    lines = ['# Stereo calibration refined online by stereo_vo_ros (rig_calibration.py): the',
             "# right camera's residual rotation (rectification_matrix), focal ratio and",
             '# principal point folded in. Describes the images as raw input (input_kind: raw).']
    return '\n'.join(lines + block('left', left) + block('right', right)) + '\n'
