"""
The node's ROS parameters: one per ``Config`` field, named ``section.name``.

Holds the descriptor of each parameter (description, range; read-only unless the field is
``dynamic``), their declaration on a node with the check of the overrides
(``--params-file``, ``parameter_overrides``), the pick of the changes allowed at run time,
and the check of the params files of a command line before rcl reads them. Values and ranges
are in the units of the ``Config`` fields (each field's doc names them).
"""

from __future__ import annotations

import array
import dataclasses
import pathlib
from typing import Any

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
import yaml

from ..config import Config, from_flat
from ..errors import ConfigError


def parameter_descriptor(name: str, field: dataclasses.Field) -> ParameterDescriptor:
    """
    Build the ROS parameter descriptor of one ``Config`` field.

    The description is the field's doc (plus its choices); integer and floating-point ranges
    come from ``lo``/``hi``; the parameter is read-only unless the field is ``dynamic``.
    Floating-point and list fields use dynamic typing so that a params file may write ``1``
    for ``1.0``; ``Config`` then checks and converts the value.
    """
    meta = field.metadata
    default = field.default if field.default is not dataclasses.MISSING else \
        field.default_factory()
    desc = ParameterDescriptor(name=name, description=str(meta.get('doc', '')),
                               read_only=not meta.get('dynamic', False))
    if meta.get('choices'):
        desc.additional_constraints = 'one of: ' + ', '.join(meta['choices'])
    lo, hi = meta.get('lo'), meta.get('hi')
    if isinstance(default, bool):
        pass
    elif isinstance(default, int):
        if lo is not None and hi is not None:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
    elif isinstance(default, float):
        desc.dynamic_typing = True
        if lo is not None and hi is not None:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    elif isinstance(default, list):
        desc.dynamic_typing = True
    return desc


def _reason(exc: ParameterException) -> str:
    """Return the useful part of an rclpy parameter exception, on one line."""
    text = ' '.join(str(exc).split())
    return text.replace('Invalid parameter value ', '').replace('Trying to set parameter ', '')


def _plain(value: Any) -> Any:
    """Parameter value as Config expects it (arrays -> lists)."""
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return list(value)
    return value


def declare_config(node: Node) -> tuple[Config, dict[str, dataclasses.Field]]:
    """
    Declare every Config field as a parameter of a node and build the Config from their values.

    Parameters
    ----------
    node : rclpy.node.Node
        The node; its parameter overrides give the initial values, else the defaults.

    Returns
    -------
    tuple of Config and dict
        The configuration, and the ``Config`` field of every parameter by name.

    Raises
    ------
    ConfigError
        An override is not a valid configuration (unknown ``section.name``, wrong type or out
        of range); the message names the parameter, its range and type.

    """
    values = {}
    declared: dict[str, dataclasses.Field] = {}
    overrides = getattr(node, '_parameter_overrides', {})  # rclpy keeps them here
    fields = {name: field for name, _, field in Config().items()}
    # Check the overrides first, for messages that name the parameter, its range and type.
    from_flat({n: _plain(p.value) for n, p in overrides.items() if n in fields})
    for name, default, field in Config().items():
        declared[name] = field
        try:
            param = node.declare_parameter(name, default, parameter_descriptor(name, field))
        except ParameterException as exc:  # out of range or of the wrong type
            given = overrides[name].value if name in overrides else default
            raise ConfigError(f'parameter {name}: {given!r} rejected ({_reason(exc)}); '
                              f'default {default!r}: {field.metadata.get("doc", "")}') \
                from None
        values[name] = _plain(param.value)
    sections = {name.partition('.')[0] for name in declared}
    unknown = sorted(n for n in overrides if n.partition('.')[0] in sections and
                     n not in declared)
    if unknown:
        raise ConfigError(f'unknown parameter(s) {unknown}; see config/stereo_vo.yaml for '
                          f'the known ones')
    return from_flat(values), declared


def config_updates(fields: dict[str, dataclasses.Field], params: list[Parameter]
                   ) -> tuple[dict[str, Any], str]:
    """
    Pick the changes of ``Config`` fields out of a request to set parameters at run time.

    Parameters
    ----------
    fields : dict
        The ``Config`` field of every declared parameter by name (``declare_config``).
    params : list of rclpy.parameter.Parameter
        The parameters to set; those that are no ``Config`` field (``use_sim_time`` and the
        like) are left out.

    Returns
    -------
    tuple of dict and str
        The new values by parameter name (as ``Config`` expects them) and ``''``, or an empty
        dict and why the request is refused (a field that cannot change at run time).

    """
    updates = {}
    for p in params:
        field = fields.get(p.name)
        if field is None:
            continue  # use_sim_time and the like
        if not field.metadata.get('dynamic', False):
            return {}, f'{p.name} cannot change at run time'
        updates[p.name] = _plain(p.value)
    return updates, ''


def check_params_files(argv: list[str]) -> None:
    """
    Read every ``--params-file`` of the command line before rcl does, for a one-line error.

    Only readability and YAML syntax are checked here: the file may hold other nodes'
    parameters too; the node checks its own values once rclpy has parsed them.

    Raises
    ------
    ConfigError
        A params file is missing, unreadable or not YAML.

    """
    for flag, path in zip(argv, argv[1:]):
        if flag != '--params-file':
            continue
        try:
            yaml.safe_load(pathlib.Path(path).read_text())
        except OSError as exc:
            raise ConfigError(f'cannot read the params file {path!r}: {exc.strerror}') \
                from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, 'problem_mark', None)
            where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
            problem = getattr(exc, 'problem', None) or ' '.join(str(exc).split())
            raise ConfigError(f'the params file {path!r} is not valid YAML: {problem}{where}') \
                from None
