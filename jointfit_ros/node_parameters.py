"""The node's ROS parameters: declared from jointfit's own specs, and run-time changes checked alike.

:func:`declare_parameters` declares every parameter of :data:`~jointfit_ros.params.NODE_PARAMS`
once (the per-joint and per-segment ones after reading ``joints`` and ``segments``) with a
descriptor that carries its description, range and choices, and returns the values;
:func:`runtime_changes` checks a ``set_parameters`` request with the same checks as at start.
"""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter

from .params import (
    JOINT_PARAMS,
    NODE_PARAMS,
    RUNTIME_PARAMS,
    SEGMENT_PARAMS,
    ConfigError,
    ParamSpec,
    check_known,
    check_value,
    range_text,
)

__all__ = ["declare_parameters", "runtime_changes"]

_ROS_TYPES = {
    "string": ParameterType.PARAMETER_STRING,
    "int": ParameterType.PARAMETER_INTEGER,
    "double": ParameterType.PARAMETER_DOUBLE,
    "bool": ParameterType.PARAMETER_BOOL,
    "string_array": ParameterType.PARAMETER_STRING_ARRAY,
}


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    text = spec.description + range_text(spec)
    if spec.choices:
        text += f" One of: {', '.join(spec.choices)}."
    # Dynamic typing: rclpy would refuse an integer for a double (and any wrong type) with a traceback
    # at start; jointfit's own checks (check_value) accept 1 for 1.0 and name the parameter otherwise.
    return ParameterDescriptor(
        type=_ROS_TYPES[spec.kind], description=text, read_only=not spec.runtime, dynamic_typing=True
    )


def _declare(node: Node, name: str, spec: ParamSpec) -> Any:
    # string arrays: no default value (rclpy cannot type an empty list); check_value gives [] for None
    param = node.declare_parameter(name, None if spec.kind == "string_array" else spec.default, _descriptor(spec))
    return param.value


def declare_parameters(node: Node) -> dict[str, Any]:
    """Declare every parameter once (joint and segment ones after reading ``joints``, ``segments``); their values.

    Raises
    ------
    ConfigError
        ``joints`` or ``segments`` invalid, or a key of the params file that names no parameter
        (a misspelt key is an error, not ignored).
    """
    values = {spec.name: _declare(node, spec.name, spec) for spec in NODE_PARAMS}
    specs = {spec.name: spec for spec in NODE_PARAMS}
    joints = check_value(specs["joints"], values["joints"], "joints")
    segments = check_value(specs["segments"], values["segments"], "segments")
    check_known(node._parameter_overrides, joints, segments)
    for owner, owned in ((joints, JOINT_PARAMS), (segments, SEGMENT_PARAMS)):
        for name in owner:
            for spec in owned:
                full = f"{name}.{spec.name}"
                values[full] = _declare(node, full, spec)
    return values


def runtime_changes(params: list[Parameter]) -> dict[str, Any] | str:
    """The checked values of a ``set_parameters`` request's run-time parameters, or why it is refused.

    Read-only parameters are left out (rclpy refuses them itself); the first value that fails
    :func:`~jointfit_ros.params.check_value` refuses the whole request (its message, naming the
    parameter, is returned). So is a value of type NOT_SET (``ros2 param delete``): the
    parameters are declared with dynamic typing, so rclpy would accept it and undeclare the
    parameter, while :func:`~jointfit_ros.params.check_value` reads ``None`` as "the default":
    the node would silently go back to the default and no later change could be set.
    """
    specs = {s.name: s for s in NODE_PARAMS}
    changes: dict[str, Any] = {}
    for p in params:
        if p.name not in RUNTIME_PARAMS:
            continue
        if p.type_ == Parameter.Type.NOT_SET:
            return f"{p.name}: cannot be unset (deleted) while the node runs; set a value instead"
        try:
            changes[p.name] = check_value(specs[p.name], p.value, p.name)
        except ConfigError as exc:
            return str(exc)
    return changes
