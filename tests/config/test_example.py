"""config/example.yaml documents every setting where it sits, with the default the code declares
(``Default X`` or ``Required`` in its comment), and shows no key the code does not declare."""

import re

import yaml

from atlas_onboard.config import load_world
from atlas_onboard.config.reference import rows
from tests.config.common import REPO

EXAMPLE = REPO / "config" / "example.yaml"
ROWS = {r.path: r for r in rows()}
KEY_NAMES = {path.rsplit(".", 1)[-1] for path in ROWS}
# Keys that only hold settings (an entity, a node section, a list of sensors...).
STRUCTURE = {"conventions", "fusion", "entities", "entities.<name>", "entities.<name>.sensors"}
STRUCTURE |= {"entities.<name>.markers", "nodes", "nodes.<entity>"}
COMMENTED_KEY = re.compile(r"^(\s*)# (\s*[a-z][a-z0-9_]*):(\s|$)")
DEFAULT = re.compile(r"\bDefault:? (\S+)")


def uncommented(text):
    """The example's lines with its commented-out keys written in, each at its column (``# key: v`` ->
    ``key: v``), so that they are read and checked like the others."""
    out = []
    for line in text.splitlines():
        m = COMMENTED_KEY.match(line)
        if m and m.group(2).strip() in KEY_NAMES:
            rest = line[len(m.group(1)) + 2 :]
            trailing = rest.find(" #")  # its comment stays at its column, aligned with the lines below
            rest = rest if trailing < 0 else rest[:trailing] + "  " + rest[trailing:]
            line = m.group(1) + rest
        out.append(line)
    return out


def schema_path(path):
    """``entities.drone1.sensors[0].id`` -> ``entities.<name>.sensors[].id``, as the declarations name it."""
    path = re.sub(r"^entities\.[^.\[]+", "entities.<name>", path)
    path = re.sub(r"^nodes\.[^.\[]+", "nodes.<entity>", path)
    return re.sub(r"\[\d+\]", "[]", path)


def occurrences(lines):
    """(declared path, line index, column) of every key of the document (not inside a pose)."""
    out = []

    def walk(node, path):
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                p = f"{path}.{k.value}" if path else k.value
                out.append((schema_path(p), k.start_mark.line, k.start_mark.column))
                if not p.endswith(".pose"):
                    walk(v, p)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                walk(item, f"{path}[{i}]")

    walk(yaml.compose("\n".join(lines)), "")
    return out


def doc_of(lines, i, column):
    """The comment that documents the key at line ``i``: its trailing comment and the comment lines
    below aligned with it, or else the comment lines just above at the key's column."""
    line = lines[i]
    trailing = line.find(" #", column)
    if trailing >= 0:
        hash_col = trailing + 1
        text = [line[hash_col:]]
        for below in lines[i + 1 :]:
            if not below.strip().startswith("#") or below.index("#") != hash_col:
                break
            text.append(below[hash_col:])
        return " ".join(text)
    text = []
    for above in reversed(lines[:i]):
        if not above.strip().startswith("#") or above.index("#") != column:
            break
        text.insert(0, above[column:])
    return " ".join(text)


def same(stated, declared):
    return yaml.safe_load(stated.rstrip(".,;:)")) == yaml.safe_load(declared)


def test_every_key_of_the_example_is_declared_with_the_default_its_comment_states():
    lines = uncommented(EXAMPLE.read_text(encoding="utf-8"))
    found = occurrences(lines)
    undeclared = sorted({p for p, _, _ in found if p not in ROWS and p not in STRUCTURE})
    assert not undeclared, f"keys in example.yaml that the code does not declare: {undeclared}"
    wrong, documented = [], set()
    for path, i, column in found:
        if path not in ROWS:
            continue
        declared = ROWS[path].default
        doc = doc_of(lines, i, column)
        stated = DEFAULT.findall(doc)
        wrong += [(path, i + 1, f"Default {s}", declared) for s in stated if not same(s, declared)]
        if "Required" in doc and declared != "required":
            wrong.append((path, i + 1, "Required", declared))
        if (declared == "required" and "Required" in doc) or (stated and all(same(s, declared) for s in stated)):
            documented.add(path)
    assert not wrong, f"example.yaml states another default than the code (key, line, says, declared): {wrong}"
    missing = [p for p in ROWS if p not in documented]
    assert not missing, f"settings example.yaml does not document with their default: {missing}"


def test_the_commented_out_keys_of_the_example_are_valid_as_written(tmp_path):
    written = tmp_path / "example.yaml"
    written.write_text("\n".join(uncommented(EXAMPLE.read_text(encoding="utf-8"))) + "\n", encoding="utf-8")
    load_world(written)  # a ConfigError names the key
    world = load_world(EXAMPLE)
    assert world.fingerprint() == load_world(written).fingerprint()
