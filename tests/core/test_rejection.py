"""One vocabulary of rejections: every reason is produced somewhere, counted under one name."""

import re
from pathlib import Path

import pytest

from atlas_onboard.core.rejection import Rejection
from atlas_onboard.counters import Counters
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import codec

PACKAGE = Path(__file__).resolve().parents[2] / "atlas_onboard"


def test_every_reason_is_produced_by_some_block():
    """No member that no code produces: each is named as ``Rejection.NAME`` outside its definition."""
    source = "\n".join(p.read_text(encoding="utf-8") for p in PACKAGE.rglob("*.py") if p.name != "rejection.py")
    named = set(re.findall(r"Rejection\.([A-Z_]+)", source))
    assert {r.name for r in Rejection} - named == set()


def test_a_reason_is_counted_under_its_counter_name():
    c = Counters()
    c.inc(Rejection.DUPLICATE)
    c.inc("rejected_duplicate")
    c.update([Rejection.BAD_STAMP, "ambiguity_resolved"])
    assert (
        c[Rejection.DUPLICATE] == 2
        and c["rejected_duplicate"] == 2
        and Rejection.DUPLICATE.counter == "rejected_duplicate"
    )
    assert c.snapshot() == {"rejected_duplicate": 2, "rejected_bad_stamp": 1, "ambiguity_resolved": 1}


def test_a_codec_rejection_is_an_atlas_error_carrying_its_reason():
    with pytest.raises(AtlasError, match=r"^tunnel_unknown_type$") as info:
        codec.decode_tunnel(1, 88, bytes(128), origin=2, fingerprint=0)
    assert isinstance(info.value, codec.RejectionError) and info.value.reason is Rejection.TUNNEL_UNKNOWN_TYPE
