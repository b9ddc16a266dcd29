"""Safe YAML reading in one parse, refusing aliases and deep nesting, with numeric lists read in bulk.

:func:`load_bounded_yaml` reads what ``yaml.load(text, Loader=CSafeLoader)`` reads and refuses what it
refuses, with the same errors, but walks libyaml's event stream once and builds the values itself:
the plain-number lists that make up most of a calibration file (a U map is ~58 000 numbers) are
converted by one ``float`` per number instead of PyYAML's resolver and constructor calls. Anything
out of the ordinary (a tag, an anchor, a merge key, a collection as a key, several documents, a
scalar PyYAML's constructor refuses) is read by PyYAML itself instead, after the same checks.

Aliases are refused because an alias bomb expands exponentially when walked; nesting is bounded
because libyaml's composer recurses once per level (it crashed the process at 100 000 levels).
Both are refused at the offending event, so a hostile document costs a few events however long
it is.
"""
from __future__ import annotations

import re
from typing import Any

import yaml
from yaml.composer import ComposerError
from yaml.nodes import ScalarNode

# libyaml's parser when PyYAML was built with it: ~10x faster than the pure-Python one.
SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

# Plain scalars that YAML 1.1 resolves as floats and ``float`` reads to the same value as PyYAML's
# constructor: what PyYAML's dumper writes for a finite float (digits, a dot, digits, an optional
# signed exponent). Others go through the resolver one by one.
_FLOAT = r"-?[0-9]+\.[0-9]+(?:e[-+][0-9]+)?"
_ONE_FLOAT = re.compile(_FLOAT)
_FLOATS_LINES = re.compile(rf"{_FLOAT}(?:\n{_FLOAT})*")
_STR_TAG = "tag:yaml.org,2002:str"
_SPECIAL_KEY_TAGS = ("tag:yaml.org,2002:merge", "tag:yaml.org,2002:value")   # handled by PyYAML's mapping code
_OPENING_EVENTS = (yaml.SequenceStartEvent, yaml.MappingStartEvent)
_CLOSING_EVENTS = (yaml.SequenceEndEvent, yaml.MappingEndEvent)
_NO_KEY = object()


class _Unusual(Exception):
    """The document needs PyYAML's own construction (see the module's docstring)."""


def check_structure(text: str, max_depth: int) -> None:
    """Raise ``ComposerError`` for an alias or for nesting deeper than ``max_depth`` in ``text``.

    Parser errors (``YAMLError``) come through as they are. The parser is lazy: a hostile document
    is refused after a few events, however long it is.
    """
    depth = 0
    for event in yaml.parse(text, Loader=SAFE_LOADER):
        if isinstance(event, yaml.AliasEvent):
            raise _alias_error(event)
        if isinstance(event, _OPENING_EVENTS):
            depth += 1
            if depth > max_depth:
                raise _depth_error(event, max_depth)
        elif isinstance(event, _CLOSING_EVENTS):
            depth -= 1


def load_bounded_yaml(text: str, max_depth: int) -> Any:
    """Return the single YAML document in ``text`` as ``yaml.load`` with the C safe loader would.

    Raises
    ------
    yaml.YAMLError
        ``ComposerError`` for an alias or nesting deeper than ``max_depth`` (see
        :func:`check_structure`); otherwise whatever ``yaml.load`` raises for ``text``.
    """
    loader = SAFE_LOADER(text)
    try:
        return _build(loader, max_depth)
    except _Unusual:
        pass
    finally:
        loader.dispose()
    check_structure(text, max_depth)
    return yaml.load(text, Loader=SAFE_LOADER)


def _alias_error(event: yaml.Event) -> ComposerError:
    return ComposerError(None, None, "aliases are not allowed", event.start_mark)


def _depth_error(event: yaml.Event, max_depth: int) -> ComposerError:
    return ComposerError(None, None, f"nested deeper than {max_depth} levels", event.start_mark)


def _build(loader: Any, max_depth: int) -> Any:
    """Build the document from ``loader``'s events; _Unusual when PyYAML must build it."""
    next_event = loader.get_event
    if not isinstance(next_event(), yaml.StreamStartEvent) or not isinstance(next_event(), yaml.DocumentStartEvent):
        raise _Unusual()       # an empty stream: PyYAML says what it is
    # One frame per open collection: [list, all-plain flag] or [dict, pending key].
    frames: list[list] = []
    root: Any = _NO_KEY
    while True:
        event = next_event()
        kind = type(event)
        if kind is yaml.ScalarEvent:
            if event.anchor is not None or event.tag is not None:
                raise _Unusual()
            value = event.value
            frame = frames[-1] if frames else None
            if frame is not None and type(frame[0]) is list and frame[1] and event.implicit[0]:
                frame[0].append(value)      # plain: kept as text, converted with its list (_close_list)
                continue
            value = _scalar(loader, event)
        elif kind is yaml.SequenceStartEvent or kind is yaml.MappingStartEvent:
            if event.anchor is not None or event.tag is not None:
                raise _Unusual()
            if len(frames) >= max_depth:
                raise _depth_error(event, max_depth)
            frames.append([[], True] if kind is yaml.SequenceStartEvent else [{}, _NO_KEY])
            continue
        elif kind is yaml.SequenceEndEvent:
            value = _close_list(loader, frames.pop())
        elif kind is yaml.MappingEndEvent:
            value = frames.pop()[0]
        elif kind is yaml.AliasEvent:
            raise _alias_error(event)
        else:
            raise _Unusual()        # no other event can come inside a document's root node
        if not frames:
            root = value
            break
        frame = frames[-1]
        container = frame[0]
        if type(container) is list:
            if frame[1]:
                _plain_to_values(loader, frame)
            container.append(value)
        elif frame[1] is _NO_KEY:
            if kind is not yaml.ScalarEvent:
                raise _Unusual()    # a collection as a key (a merge key is unusual in _scalar)
            frame[1] = value
        else:
            container[frame[1]] = value     # a repeated key: the last value wins, as in PyYAML
            frame[1] = _NO_KEY
    if not isinstance(next_event(), yaml.DocumentEndEvent) or not isinstance(next_event(), yaml.StreamEndEvent):
        raise _Unusual()       # more than one document: PyYAML's error
    return root


def _scalar(loader: Any, event: yaml.ScalarEvent) -> Any:
    """Return the value of an untagged scalar event as PyYAML's safe constructor builds it."""
    value = event.value
    if event.implicit[0] and _ONE_FLOAT.fullmatch(value):
        return float(value)
    tag = loader.resolve(ScalarNode, value, event.implicit)
    if tag == _STR_TAG:
        return value
    if tag in _SPECIAL_KEY_TAGS:
        raise _Unusual()
    node = ScalarNode(tag, value, event.start_mark, event.end_mark, event.style)
    try:
        return loader.yaml_constructors[tag](loader, node)
    except Exception:     # PyYAML's own reading raises its own error for it
        raise _Unusual() from None


def _plain_to_values(loader: Any, frame: list) -> None:
    """Turn a list frame's plain scalars, kept as text, into values one by one (a non-plain item came)."""
    texts = frame[0]
    frame[0][:] = [_plain_value(loader, text) for text in texts]
    frame[1] = False


def _plain_value(loader: Any, text: str) -> Any:
    return _scalar(loader, yaml.ScalarEvent(None, None, (True, False), text))


def _close_list(loader: Any, frame: list) -> list:
    """Return a finished list; all-plain lists of floats in one go, others item by item."""
    items = frame[0]
    if not frame[1] or not items:
        return items
    joined = "\n".join(items)
    # one line per item: a plain scalar may hold a line break (folded blank lines)
    if joined.count("\n") == len(items) - 1 and _FLOATS_LINES.fullmatch(joined):
        return list(map(float, items))
    _plain_to_values(loader, frame)
    return frame[0]
