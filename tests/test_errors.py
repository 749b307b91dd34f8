"""The error hierarchy's one-line messages: a ConfigError names the file and the field before the
problem, and a read failure says why in the system's words."""

from __future__ import annotations

import pytest

from atlas_onboard.errors import AtlasError, ConfigError, GeometryError, read_failure


@pytest.mark.parametrize(
    ("path", "file", "message"),
    [
        ("entities.d1.sensors[0].id", "w.yaml", "w.yaml: entities.d1.sensors[0].id: expected an int"),
        ("", "w.yaml", "w.yaml: expected an int"),
        ("rate_hz", None, "rate_hz: expected an int"),
        ("", None, "expected an int"),
    ],
)
def test_a_config_error_names_its_file_and_field_before_the_problem(path, file, message):
    err = ConfigError(path, "expected an int", file)
    assert str(err) == message
    assert (err.path, err.problem, err.file) == (path, "expected an int", file)
    assert isinstance(err, AtlasError) and isinstance(GeometryError("x"), AtlasError)


def test_a_read_failure_is_the_systems_reason_or_the_decoders(tmp_path):
    try:
        (tmp_path / "missing").read_text()
    except OSError as exc:
        assert read_failure(exc) == "No such file or directory"
    bad = tmp_path / "latin1"
    bad.write_bytes(b"\xe9")
    with pytest.raises(UnicodeDecodeError) as info:
        bad.read_text(encoding="utf-8")
    assert read_failure(info.value) == str(info.value)
    assert read_failure(OSError("no errno")) == "no errno"  # no strerror: its text
