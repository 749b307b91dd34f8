"""The generated dialect: made by mavgen into a cache keyed by a hash, atomically, regenerated when
damaged; and the numbers in docs/wire-format.md are the generated ones."""

import os
import re
import sys
from pathlib import Path

from atlas_onboard.mavlink import codec, dialect

DOC = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"


def test_generated_into_a_cache_keyed_by_the_hash_and_regenerated_when_damaged(tmp_path, monkeypatch):
    monkeypatch.setenv("ATLAS_ONBOARD_CACHE", str(tmp_path))
    monkeypatch.setattr(dialect, "_cache", {})
    module = dialect.load()
    key = dialect.digest()
    path = tmp_path / f"atlas_dialect_{key}.py"
    # No staging file left behind; the bytecode beside it, whatever PYTHONDONTWRITEBYTECODE says.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, "__pycache__"])
    pyc = tmp_path / "__pycache__" / f"atlas_dialect_{key}.{sys.implementation.cache_tag}.pyc"
    assert pyc.is_file() and pyc.stat().st_size > 100_000
    assert module.MAVLink_atlas_observation_message.id == 43100
    assert module.MAVLink_atlas_fused_pose_message.id == 43101
    assert module.MAVLink_tunnel_message.id == 385  # common.xml is included
    assert dialect.load() is module  # one module per process
    path.write_text("this is not python (", encoding="utf-8")  # a damaged cache file
    monkeypatch.setattr(dialect, "_cache", {})
    again = dialect.load()
    assert again.MAVLink_atlas_observation_message.crc_extra == module.MAVLink_atlas_observation_message.crc_extra
    assert "this is not python" not in path.read_text(encoding="utf-8")
    assert pyc.stat().st_mtime >= path.stat().st_mtime  # compiled again from the new file


def test_common_xml_is_found_in_the_installed_pymavlink():
    assert (dialect.definitions_dir() / "common.xml").is_file()
    assert len(dialect.digest()) == 16


def test_ids_in_the_unallocated_range_and_not_in_common():
    d = dialect.load()
    ours = {cls.id for cls in d.mavlink_map.values() if getattr(cls, "msgname", "").startswith("ATLAS_")}
    assert ours == {43100, 43101} and all(43000 <= i <= 49999 for i in ours)


def test_the_document_states_the_generated_numbers():
    text = DOC.read_text(encoding="utf-8")
    d = dialect.load()
    rows = {
        m[0]: (int(m[1]), int(m[2]), int(m[3]))
        for m in re.findall(r"^\| (\w+) .*?\| (\d+) \| (\d+) \| (\d+)", text, re.M)
    }
    for name in ("ATLAS_OBSERVATION", "ATLAS_FUSED_POSE", "TUNNEL"):
        cls = getattr(d, f"MAVLink_{name.lower()}_message")
        msg_id, crc, _size = rows[name]
        assert (msg_id, crc) == (cls.id, cls.crc_extra), name
    # 87 bytes, then the extensions frame_remaining (1 byte) and covariance (21 floats).
    assert rows["ATLAS_OBSERVATION"][2] + 1 + 84 == d.MAVLink_atlas_observation_message.unpacker.size == 172
    assert rows["ATLAS_FUSED_POSE"][2] + 16 == d.MAVLink_atlas_fused_pose_message.unpacker.size
    assert 'struct.Struct("<QI3f4f3f3f4fHHHB")' in text and codec.TUNNEL_STRUCT.format == "<QI3f4f3f3f4fHHHB"
    # Every field of the observation table is at the offset the generated layout puts it.
    offsets = dict(re.findall(r"^\| (\d+) \| (\w+)(?:\[\d+\])? \| (?:uint|float|char)", text, re.M)[:19])
    layout, at = {}, 0
    cls = d.MAVLink_atlas_observation_message
    sizes = {"Q": 8, "I": 4, "f": 4, "H": 2, "B": 1}
    fmt = re.findall(r"(\d*)([QIfHB])", cls.unpacker.format)
    for name, (count, code) in zip(cls.ordered_fieldnames, fmt, strict=True):
        layout[name] = at
        at += sizes[code] * int(count or 1)
    assert {name: int(off) for off, name in offsets.items()} == layout


PLANTED = "PLANTED = True\nMAVLink = None\n"


def _plant(monkeypatch, cache):
    monkeypatch.setenv("ATLAS_ONBOARD_CACHE", str(cache))
    monkeypatch.setattr(dialect, "_cache", {})
    (cache / f"atlas_dialect_{dialect.digest()}.py").write_text(PLANTED, encoding="utf-8")


def test_a_cache_writable_by_others_is_never_imported(tmp_path, monkeypatch):
    cache = tmp_path / "shared"
    cache.mkdir()
    cache.chmod(0o777)  # a shared /tmp-like directory: anyone could have planted the module
    _plant(monkeypatch, cache)
    module = dialect.load()
    assert not hasattr(module, "PLANTED") and module.MAVLink_atlas_observation_message.id == 43100
    assert not str(module.__file__).startswith(str(cache))


def test_a_module_writable_by_others_or_owned_by_another_user_is_never_imported(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    _plant(monkeypatch, cache)
    planted = cache / f"atlas_dialect_{dialect.digest()}.py"
    planted.chmod(0o666)
    assert not hasattr(dialect.load(), "PLANTED")
    if os.getuid() == 0:  # as root: the file handed to another user
        planted.chmod(0o644)
        os.chown(planted, 65534, 65534)
        monkeypatch.setattr(dialect, "_cache", {})
        assert not hasattr(dialect.load(), "PLANTED")
