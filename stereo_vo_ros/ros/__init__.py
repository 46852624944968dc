"""
ROS 2 adapter of stereo_vo_ros: the node, message conversions, stereo sync and a bag player.

Only this subpackage imports rclpy and ROS messages; the core package stays ROS-free.
``sync``, ``tf_tree.TransformTree`` and ``dds`` are pure Python and work without rclpy, and so
does this module: ``node_main`` (the ``stereo_vo_node`` entry point) imports the node only when
it runs, so that a pip install without ROS gets one line naming what to install.
"""

from __future__ import annotations

import sys

from ..errors import MissingDependencyError

#: What a user without the ROS 2 Python packages should do.
ROS_INSTALL_HINT = ('source a ROS 2 Jazzy install (source /opt/ros/jazzy/setup.bash) or '
                    'install the ROS extra of the package: pip install "stereo_vo_ros[ros]" '
                    '(from a checkout: pip install ".[ros]")')


def missing_ros(exc: ModuleNotFoundError, what: str) -> MissingDependencyError:
    """
    Turn a failed import of a ROS package into an error that names the fix.

    Parameters
    ----------
    exc : ModuleNotFoundError
        The import error; re-raised unchanged by the caller when it is about this package.
    what : str
        What needed it (``the node``, ``the demo``).

    Returns
    -------
    MissingDependencyError
        One line: the missing module and what to install.

    """
    return MissingDependencyError(f'{what} needs the ROS 2 Python package {exc.name!r}, which '
                                  f'is not installed: {ROS_INSTALL_HINT}')


def is_ours(exc: ModuleNotFoundError) -> bool:
    """Return True when the missing module is part of stereo_vo_ros itself (a real bug)."""
    return (exc.name or '').split('.')[0] == 'stereo_vo_ros'


def node_main(args: list[str] | None = None) -> int:
    """
    Entry point ``stereo_vo_node``: run the node (see ``node.main``).

    Returns
    -------
    int
        The node's exit code; 2 with one line on stderr when ROS packages are missing.

    """
    try:
        from .node import main
    except ModuleNotFoundError as exc:
        if is_ours(exc):
            raise
        print(f'stereo_vo_node: {missing_ros(exc, "the node")}', file=sys.stderr)
        return 2
    return main(args)
