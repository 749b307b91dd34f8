"""The core is pure: it imports nothing but numpy, scipy, the standard library and itself."""

import ast
from pathlib import Path

import atlas_onboard.core as core

ALLOWED_TOP = {"numpy", "scipy", "atlas_onboard", "__future__"}
FORBIDDEN_STDLIB = {"socket", "time", "threading", "asyncio", "subprocess", "os", "io", "select", "logging.handlers"}


def test_core_imports_no_io():
    for path in Path(core.__file__).parent.rglob("*.py"):  # subpackages (core/graph/) included
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                assert name not in FORBIDDEN_STDLIB and top not in FORBIDDEN_STDLIB, f"{path.name} imports {name}"
                if top == "atlas_onboard":
                    assert name.startswith(("atlas_onboard.core", "atlas_onboard.errors")), (
                        f"{path.name} imports {name}"
                    )
                assert top in ALLOWED_TOP or top in _stdlib(), f"{path.name} imports {name}"


def _stdlib():
    import sys

    return sys.stdlib_module_names
