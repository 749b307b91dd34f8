"""YAML in: the document as PyYAML's safe loader reads it, and a one-line ConfigError naming the file,
the field and the line for a repeated key, a malformed or unreadable file."""

from __future__ import annotations

import pytest
import yaml

from atlas_onboard.config.yamlio import read_yaml
from atlas_onboard.errors import ConfigError


def _write(tmp_path, text: str):
    path = tmp_path / "w.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_a_valid_file_reads_as_the_safe_loader_reads_it(tmp_path):
    text = "a: 1\nb: [x, {c: 2.5}]\nanchor: &p {x: 1}\nuse: *p\n"
    assert read_yaml(_write(tmp_path, text)) == yaml.safe_load(text)


def test_an_empty_file_is_none(tmp_path):
    assert read_yaml(_write(tmp_path, "# only a comment\n")) is None


def test_a_repeated_key_is_named_with_its_field_path_and_line(tmp_path):
    path = _write(tmp_path, "entities:\n  drone:\n    sensors:\n      - {name: a, name: b}\n")
    with pytest.raises(ConfigError) as err:
        read_yaml(path)
    assert err.value.path == "entities.drone.sensors[0].name"
    assert err.value.problem == "duplicate key 'name' (line 4)"
    assert str(err.value) == f"{path}: entities.drone.sensors[0].name: duplicate key 'name' (line 4)"


def test_a_repeated_top_level_key_is_refused(tmp_path):
    with pytest.raises(ConfigError) as err:
        read_yaml(_write(tmp_path, "a: 1\nb: 2\na: 3\n"))
    assert err.value.path == "a" and err.value.problem == "duplicate key 'a' (line 3)"


def test_a_tree_of_aliases_is_walked_once_per_node(tmp_path):
    # Nine levels of ten aliases each: 10**9 paths through the tree, ten nodes.
    lines = ["l0: &l0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"l{k}: &l{k} [{', '.join([f'*l{k - 1}'] * 10)}]" for k in range(1, 10)]
    data = read_yaml(_write(tmp_path, "\n".join(lines) + "\n"))
    assert data["l9"][0][0][0][0][0][0][0][0][0] == data["l0"] == ["x"] * 10


def test_malformed_yaml_says_where(tmp_path):
    with pytest.raises(ConfigError) as err:
        read_yaml(_write(tmp_path, "a: [1, 2\nb: 3\n"))
    assert err.value.problem.startswith("invalid YAML: line ")
    assert "\n" not in str(err.value)


def test_an_unreadable_file_is_one_line(tmp_path):
    with pytest.raises(ConfigError) as err:
        read_yaml(tmp_path / "missing.yaml")
    assert err.value.problem == "cannot read file: No such file or directory"
    (tmp_path / "latin1.yaml").write_bytes(b"a: \xe9\n")
    with pytest.raises(ConfigError) as err:
        read_yaml(tmp_path / "latin1.yaml")
    assert err.value.problem.startswith("cannot read file: ") and "\n" not in str(err.value)
