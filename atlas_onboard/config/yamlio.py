"""YAML in: one-line errors for an unreadable or malformed file, and for a mapping that repeats a key
(which YAML would otherwise let silently override the first)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from atlas_onboard.config.fields import join
from atlas_onboard.errors import ConfigError, read_failure


def _duplicate_key(node: yaml.Node, path: str = "", seen_nodes: set[int] | None = None) -> tuple[str, str] | None:
    """The field path and description of the first key a mapping repeats, in the composed YAML tree
    (a repeated key would otherwise silently override the first), or None. An alias is the node it
    names: each node is visited once, so a tree of aliases cannot make this walk explode."""
    seen_nodes = set() if seen_nodes is None else seen_nodes
    if id(node) in seen_nodes:
        return None
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen: set[object] = set()
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else id(key_node)
            child = join(path, str(key))
            if key in seen:
                return child, f"duplicate key {key!r} (line {key_node.start_mark.line + 1})"
            seen.add(key)
            found = _duplicate_key(value_node, child, seen_nodes)
            if found is not None:
                return found
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            found = _duplicate_key(item, join(path, i), seen_nodes)
            if found is not None:
                return found
    return None


def read_yaml(path: Path) -> Any:
    """Parse a YAML file; an unreadable or malformed file, or a mapping that repeats a key, is a
    one-line ConfigError."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("", f"cannot read file: {read_failure(exc)}", str(path)) from None
    try:
        tree = yaml.compose(text, Loader=yaml.SafeLoader)
        if tree is None:
            return None
        duplicate = _duplicate_key(tree)
        if duplicate is not None:
            raise ConfigError(*duplicate, str(path))
        return yaml.SafeLoader(text).construct_document(tree)
    except RecursionError:
        raise ConfigError("", "invalid YAML: nested too deeply", str(path)) from None
    except yaml.YAMLError as exc:
        marked = isinstance(exc, yaml.MarkedYAMLError)  # the parser's errors, with where and what
        mark = (exc.problem_mark or exc.context_mark) if marked else None
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = (exc.problem if marked else None) or str(exc).splitlines()[0]
        raise ConfigError("", f"invalid YAML: {where}{problem}", str(path)) from None
