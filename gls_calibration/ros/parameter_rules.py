"""Check that a node holds what each ``-p`` rule of its command line asked for.

rcl reads ``-p name:=value`` as YAML and merges it with the ``--params-file`` values. A rule whose
value has another type than the file's (``grid.size_mm:=abc`` over 190.0), an empty list
(``grid.ring_radii_mm:=[]``, which rcl reads as no value), or a rule for a parameter that two files
set (``head.working_distance_mm`` is in config/head.yaml and config/sim.yaml) is dropped without a
word: the node starts with the file's value. Comparing each rule with the value the node declared afterwards catches
every such rule, whatever its cause, without re-implementing rcl's typing.
"""
from __future__ import annotations

import fnmatch
import math
from collections.abc import Sequence
from typing import Any, Optional

import yaml
from rclpy.node import Node

_TRUE = {"y", "yes", "true", "on"}
_FALSE = {"n", "no", "false", "off"}
_SPECIAL_FLOATS = {".nan": math.nan, ".inf": math.inf, "+.inf": math.inf, "-.inf": -math.inf}


def parameter_rules(argv: Sequence[str]) -> list[str]:
    """Return the ``-p``/``--param`` rules among the ROS arguments of ``argv``, in their order.

    The ROS arguments run from ``--ros-args`` to ``--`` or the end. rcl applies the rules in this
    order: the last one of a name wins.
    """
    rules, inside, tokens = [], False, iter(argv)
    for token in tokens:
        if token in ("--ros-args", "--"):
            inside = token == "--ros-args"
        elif inside and token in ("-p", "--param"):
            value = next(tokens, None)
            if value is not None:
                rules.append(value)
    return rules


def _reaches(target: str, node: Node) -> Optional[str]:
    """Return the parameter name of the rule ``target`` when it reaches ``node``, else None.

    ``name`` reaches every node; ``node:name`` the node whose full name matches ``node``.
    """
    prefix, colon, name = target.rpartition(":")
    if not colon:
        return target
    full_name = node.get_fully_qualified_name()
    pattern = "/" + prefix.lstrip("/")
    if pattern == full_name or fnmatch.fnmatchcase(full_name, pattern.replace("**", "*")):
        return name
    return None


def _scalar(text: str, like: Any) -> tuple[bool, Any]:
    """(readable, value): ``text`` read as a scalar of the kind of ``like`` (the node's value)."""
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return isinstance(like, str), text[1:-1]
    if isinstance(like, bool):
        lowered = text.lower()
        return lowered in _TRUE | _FALSE, lowered in _TRUE
    if isinstance(like, int):
        try:
            return True, int(text, 0)
        except ValueError:
            return False, None
    if isinstance(like, float):
        if text.lower() in _SPECIAL_FLOATS:
            return True, _SPECIAL_FLOATS[text.lower()]
        try:
            return True, float(text)
        except ValueError:
            return False, None
    return True, text


def _same(rule_value: Any, held: Any) -> bool:
    """Return True when the node's value ``held`` is the rule's (NaN equals NaN)."""
    if isinstance(held, float) and isinstance(rule_value, (int, float)) and not isinstance(rule_value, bool):
        return rule_value == held or (math.isnan(held) and math.isnan(rule_value))
    return type(rule_value) is type(held) and rule_value == held


def rule_applied(text: str, held: Any) -> bool:
    """Return True when ``held``, the value the node declared, is what the rule value ``text`` says."""
    stripped = text.strip()
    is_list = stripped.startswith("[") and stripped.endswith("]")
    if held is None:                      # rcl sets nothing for "[]"
        return is_list and not stripped[1:-1].strip()
    if isinstance(held, str):
        return _same(_scalar(text, held)[1], held) and not is_list
    if not hasattr(held, "__len__"):
        readable, value = _scalar(text, held)
        return readable and _same(value, held)
    items = list(held)
    if not is_list:
        return False
    try:
        parsed = yaml.safe_load(stripped)     # only to split the list; each element is read below
    except yaml.YAMLError:
        return False
    if not isinstance(parsed, list):
        return False
    # PyYAML's typing is not rcl's (it reads 1e3 as text): read each element's text as the node's kind
    parts = [part if isinstance(part, str) else yaml.safe_dump(part).splitlines()[0] for part in parsed]
    if len(parts) != len(items):
        return False
    for part, item in zip(parts, items):
        readable, value = _scalar(part, item)
        if not (readable and _same(value, item)):
            return False
    return True


def unapplied_rule_problem(node: Node, argv: Sequence[str]) -> str:
    """Say why a ``-p`` rule of ``argv`` that reaches ``node`` is not what the node holds.

    Empty when every one is. Only parameters the node declares are checked; the last rule of a name
    counts.
    """
    last: dict[str, tuple[str, str]] = {}
    for rule in parameter_rules(argv):
        target, assign, text = rule.partition(":=")
        name = _reaches(target, node) if assign else None
        if name is not None and node.has_parameter(name):
            last[name] = (rule, text)
    for name, (rule, text) in last.items():
        held = node.get_parameter(name).value
        if not rule_applied(text, held):
            kind = type(held).__name__ if held is not None else "no value"
            shown = list(held) if hasattr(held, "tolist") else held
            return (f"parameter {name}: the rule -p {rule} was not applied, the node holds {shown!r} "
                    f"({kind}). rcl drops a -p rule without a word when its value has another type than a "
                    "parameter file's, when it is [] (read as no value), or when two parameter files set the "
                    "parameter: give a value of the parameter's type, or set it in one parameter file")
    return ""
