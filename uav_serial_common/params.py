"""Parameters of the drivers: one table of specs, declared with descriptors, checked then applied.

Every driver describes its parameters once, as a tuple of `ParamSpec`: type (from the default),
description, range, a one-of choice for strings, a check of its own, and whether it may change
at runtime. From that table:

- `declare_parameters()` declares them all with `ParameterDescriptor`s (ranges, read-only,
  ``additional_constraints``) and returns their values, arrays that were not given as ``[]``;
- `check_values()` is the start-up check (a driver refuses to start with a bad value);
  `declare_and_check()` does both and raises with every problem;
- `ParameterBinding` follows the ROS 2 demos' pattern for runtime changes: the on-set callback
  checks *every* parameter of a set before anything happens, then an optional ``commit`` does
  what must succeed for the set to be accepted (a driver writing a setting to its device and
  waiting for the device to confirm it, undoing what it already wrote when a later write fails);
  only an accepted set reaches ``apply`` (the post-set callback), which updates the driver's
  own configuration. A refused set therefore changes nothing at all.

rclpy itself enforces types, ranges and read-only from the descriptors before the callbacks run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

Check = Callable[[Any], str]
"""Return why a value is not acceptable, or '' when it is."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of a driver: its default (or array type), meaning and limits."""

    name: str
    default: Any
    description: str
    read_only: bool = False
    int_range: Optional[Tuple[int, int]] = None
    float_range: Optional[Tuple[float, float]] = None
    choices: Tuple[str, ...] = ()
    check: Optional[Check] = None
    startup_only: bool = False
    """Read once at start (it shapes the node); a runtime change is refused with the reason."""

    def problem(self, value: Any) -> str:
        """Return why `value` is not acceptable for this parameter, or ''."""
        if self.choices and value not in self.choices:
            return f"{self.name} must be one of {', '.join(self.choices)}, got {value!r}"
        if self.check is not None:
            return self.check(value)
        return ''

    def descriptor(self) -> ParameterDescriptor:
        """Return the ROS descriptor: description, range, read-only, the one-of choices."""
        constraints = f"one of: {', '.join(self.choices)}" if self.choices else ''
        if self.startup_only:
            constraints = '; '.join(x for x in (constraints, 'read at start only') if x)
        desc = ParameterDescriptor(description=self.description, read_only=self.read_only,
                                   additional_constraints=constraints)
        if self.int_range is not None:
            desc.integer_range = [IntegerRange(from_value=self.int_range[0],
                                               to_value=self.int_range[1], step=1)]
        if self.float_range is not None:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(self.float_range[0]), to_value=float(self.float_range[1]),
                step=0.0)]
        return desc


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> Dict[str, Any]:
    """Declare every spec on `node`; return the values (arrays not given as ``[]``)."""
    values: Dict[str, Any] = {}
    for spec in specs:
        node.declare_parameter(spec.name, spec.default, spec.descriptor())
        try:
            value = node.get_parameter(spec.name).value
        except ParameterUninitializedException:
            value = None
        if isinstance(spec.default, Parameter.Type):
            # An array declared by its type stays uninitialized when not given: empty.
            value = list(value or [])
        values[spec.name] = value
    return values


def check_values(specs: Iterable[ParamSpec], values: Mapping[str, Any]) -> List[str]:
    """Return the problems of `values` (one line each), for the start-up check."""
    problems = []
    for spec in specs:
        if spec.name in values:
            problem = spec.problem(values[spec.name])
            if problem:
                problems.append(problem)
    return problems


def declare_and_check(node: Node, specs: Sequence[ParamSpec]) -> Dict[str, Any]:
    """Declare every spec on `node` and return the values; raise ValueError naming every bad one.

    The start-up check of a node that refuses to start with a bad value (``run_node`` prints the
    reason as one line).
    """
    values = declare_parameters(node, specs)
    problems = check_values(specs, values)
    if problems:
        raise ValueError('; '.join(problems))
    return values


Commit = Callable[[Dict[str, Any]], Tuple[bool, str]]
Apply = Callable[[Dict[str, Any]], None]


class ParameterBinding:
    """Runtime parameter changes of a node: check all, then commit, then apply.

    ``commit(changes)`` (optional) runs inside the on-set callback once every parameter of the
    set passed its checks; it returns (accepted, reason) and must leave nothing changed when it
    refuses. ``apply(changes)`` runs after rclpy has stored an accepted set. Both get a dict of
    name to new value of the parameters in the set.
    """

    def __init__(self, node: Node, specs: Sequence[ParamSpec], apply: Apply,
                 commit: Optional[Commit] = None) -> None:
        self._specs = {spec.name: spec for spec in specs}
        self._apply = apply
        self._commit = commit
        self._log = node.get_logger()
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._post_set)

    def _on_set(self, params: List[Parameter]) -> SetParametersResult:
        changes = {param.name: param.value for param in params}
        problems = []
        for name, value in changes.items():
            spec = self._specs.get(name)
            if spec is None:
                continue
            if spec.startup_only:
                problems.append(f'{name} is read at start only; restart the node to change it')
                continue
            problem = spec.problem(value)
            if problem:
                problems.append(problem)
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        if self._commit is not None:
            try:
                ok, reason = self._commit(changes)
            except Exception as exc:  # noqa: BLE001 - a refusal, never an exception in rclpy
                self._log.error(f'parameter change failed: {exc!r}')
                ok, reason = False, f'internal error: {exc!r}'
            if not ok:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _post_set(self, params: List[Parameter]) -> None:
        try:
            self._apply({param.name: param.value for param in params})
        except Exception as exc:  # noqa: BLE001 - rclpy would raise it into the service
            self._log.error(f'applying parameters failed: {exc!r}')
