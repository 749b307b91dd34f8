"""docs/settings.md is the table the declarations make today."""

from atlas_onboard.config.reference import markdown, rows
from tests.config.common import REPO


def test_the_settings_page_is_current():
    page = (REPO / "docs" / "settings.md").read_text(encoding="utf-8")
    assert page == markdown(), "docs/settings.md is stale: python -m atlas_onboard.config.reference > docs/settings.md"


def test_every_row_says_what_the_setting_means_and_no_key_is_listed_twice():
    table = rows()
    assert all(r.doc for r in table)
    paths = [r.path for r in table]
    assert len(paths) == len(set(paths))
