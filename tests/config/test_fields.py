"""The declarations: every declared default passes its own check, and a number just outside its
declared range is refused with that range in the message."""

import math

import pytest

from atlas_onboard.config.fields import REQUIRED, check, declared, kind_of
from atlas_onboard.config.reference import SECTIONS
from atlas_onboard.errors import ConfigError

CLASSES = sorted({cls for _, cls, _ in SECTIONS}, key=lambda c: c.__name__)
SCALARS = (bool, int, float, str)


def _plain(default):
    """The YAML value of a default (an enum's string), or None for no default or a section's."""
    value = default.value if hasattr(default, "value") else default
    return value if default is not REQUIRED and isinstance(value, SCALARS) else None


def settings(only_numbers=False):
    for cls in CLASSES:
        for name, f in declared(cls).items():
            kind = kind_of(cls, name)
            if only_numbers and (kind not in (int, float) or f.metadata["lo"] is None):
                continue
            if not only_numbers and _plain(f.default) is None:
                continue
            yield pytest.param(cls, name, id=f"{cls.__name__}.{name}")


@pytest.mark.parametrize(("cls", "name"), list(settings()))
def test_each_declared_default_passes_its_own_check(cls, name):
    f = declared(cls)[name]
    assert check(cls, name, _plain(f.default), "x") == f.default


@pytest.mark.parametrize(("cls", "name"), list(settings(only_numbers=True)))
def test_a_number_just_outside_its_range_is_refused_naming_the_range(cls, name):
    meta = declared(cls)[name].metadata
    kind = kind_of(cls, name)
    lo, hi = meta["lo"], meta["hi"]
    step = 1 if kind is int else max(abs(hi), 1.0) * 1e-9
    below = lo if meta["lo_open"] else lo - step
    for bad in (below, hi + step):
        value = int(bad) if kind is int else bad
        with pytest.raises(ConfigError) as info:
            check(cls, name, value, "a.b")
        assert info.value.path == "a.b"
        assert (f"[{int(lo)}, {int(hi)}]" if kind is int else meta["within"]) in info.value.problem
    inside = (lo + hi) / 2 if math.isfinite(lo + hi) else lo
    assert check(cls, name, int(inside) if kind is int else inside, "a.b") == pytest.approx(inside, abs=1)
