"""Every example in ``examples/`` runs and does what it says (examples are tests too)."""

from __future__ import annotations

from load_file import ROOT, load_module

EXAMPLES = ROOT / "examples"


def _load(name: str):
    return load_module(EXAMPLES / f"{name}.py", f"example_{name}")


def test_every_example_is_tested() -> None:
    assert {p.stem for p in EXAMPLES.glob("*.py")} == {"quickstart"}


def test_quickstart_localizes_from_one_range() -> None:
    assert _load("quickstart").main(particles=3000) < 0.3
