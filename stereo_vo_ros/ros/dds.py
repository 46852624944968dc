"""
DDS transport facts the node acts on: where its Fast DDS profiles are, and which one it uses.

Why the node cares: Fast DDS (the default RMW of ROS 2 Jazzy) sends between processes of one
host through a shared-memory segment that belongs to the WRITER and holds 512 kB by default.
A 1241x376 mono8 image is 467 kB: when a camera driver publishes the left and the right image
back to back, the second one needs the memory of the first, and a best-effort reader loses the
first unless it has already copied it out (measured: about a quarter of the left images lost
at 10 Hz). A reliable reader gets a resend instead, so a reliable publisher is served fully by
a reliable subscription (``ros.qos: auto`` chooses that), but nothing on the reader's side can
enlarge the writer's segment. What the reader can do is not take part in shared memory: its
participant then offers only UDP, and the writer sends the images over loopback UDP, where the
kernel's socket receive buffer (``net.core.rmem_max`` caps it) holds the burst.

So ``stereo_vo_node`` (the process entry point, not a composed node) starts its participant
with ``config/fastdds_node.xml`` (UDPv4 only, 16 MB receive buffer) when the user has not chosen
a profile and the kernel allows a receive buffer of at least ``MIN_RMEM_BYTES``; otherwise it
keeps Fast DDS's defaults and says why. The other remedy, for the publishing process, is
``config/fastdds_large_images.xml`` (a 16 MB segment).
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
from typing import Mapping

PACKAGE = 'stereo_vo_ros'
#: The node's own Fast DDS profile (UDP only, large receive buffer).
NODE_PROFILE = 'fastdds_node.xml'
#: The profile for the process that publishes the images (16 MB shared-memory segment).
PUBLISHER_PROFILE = 'fastdds_large_images.xml'
#: Environment variables Fast DDS reads its XML profiles from (2.x, and 3.x).
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
#: Smallest ``net.core.rmem_max`` (bytes) with which the UDP profile holds two 1280x720 mono8
#: images in flight; below it the shared-memory default loses fewer images.
MIN_RMEM_BYTES = 4 * 1024 * 1024
RMEM_MAX_PATH = Path('/proc/sys/net/core/rmem_max')
FASTDDS_RMWS = ('', 'rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')


def config_path(name: str) -> Path:
    """
    Path of an installed file of the package's ``config/`` folder.

    Looks in the ament share folder (colcon or a ROS install), then in ``<prefix>/share`` of a
    pip install, then in the source tree; returns the first that exists (else the last).
    """
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory(PACKAGE)) / 'config' / name)
    except Exception:  # not installed with ament, or ament_index missing: try the others
        pass
    candidates.append(Path(sys.prefix) / 'share' / PACKAGE / 'config' / name)
    candidates.append(Path(__file__).resolve().parents[2] / 'config' / name)
    for path in candidates:
        if path.is_file():
            return path
    return candidates[-1]


def rmem_max(path: Path = RMEM_MAX_PATH) -> int | None:
    """Kernel cap of a socket's receive buffer (bytes), or None where unknown."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def choose_node_profile(environ: Mapping[str, str], rmem: int | None
                        ) -> tuple[str | None, str]:
    """
    Decide the Fast DDS profile of the node's process.

    Parameters
    ----------
    environ : mapping
        The process environment.
    rmem : int or None
        ``net.core.rmem_max`` in bytes (None: unknown).

    Returns
    -------
    tuple
        ``(profile path or None, reason)``: the path to put in
        ``FASTRTPS_DEFAULT_PROFILES_FILE`` (None: leave the environment alone) and a sentence
        for the log.

    """
    rmw = environ.get('RMW_IMPLEMENTATION', '')
    if rmw not in FASTDDS_RMWS:
        return None, f'RMW {rmw}: DDS transport left to its defaults'
    for var in PROFILE_VARIABLES:
        if environ.get(var):
            return None, f'Fast DDS profile from {var}={environ[var]}'
    if rmem is None or rmem < MIN_RMEM_BYTES:
        have = 'unknown' if rmem is None else f'{rmem} bytes'
        return None, (
            f'Fast DDS defaults kept: net.core.rmem_max is {have}, below the '
            f'{MIN_RMEM_BYTES} the UDP receive profile needs. A best-effort publisher of large '
            'images over shared memory loses some of them; raise it (sudo sysctl -w '
            'net.core.rmem_max=16777216) or start the publisher with '
            f'FASTRTPS_DEFAULT_PROFILES_FILE={config_path(PUBLISHER_PROFILE)}')
    path = config_path(NODE_PROFILE)
    if not path.is_file():
        return None, f'Fast DDS defaults kept: {path} not found'
    return str(path), (f'Fast DDS profile {path}: images arrive over UDP with a 16 MB receive '
                       'buffer, which no publisher QoS can overflow with a stereo pair (set '
                       'FASTRTPS_DEFAULT_PROFILES_FILE to choose another profile)')


def apply_node_profile(environ: os._Environ | dict | None = None) -> str:
    """Choose the node's profile (``choose_node_profile``), set it in ``environ``; the reason."""
    environ = os.environ if environ is None else environ
    for var in PROFILE_VARIABLES:  # the launch file passes an empty one for "not chosen"
        if var in environ and not environ[var]:
            del environ[var]
    path, reason = choose_node_profile(environ, rmem_max())
    if path is not None:
        environ[PROFILE_VARIABLES[0]] = path
    return reason
