"""numba is imported only when a compiled kernel first runs: ``relloc serve`` takes the NumPy step
by default, and numba's import alone (llvmlite, scipy) is more resident memory than a serve's
whole budget, so neither the command line nor a serve on the NumPy path may import it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from relloc.filter import compiled

_SERVE = textwrap.dedent(
    """
    import sys
    import time
    from typing import Any

    import relloc.cli
    from relloc.filter import compiled
    from relloc.live import LiveServer, event_messages, simulated_team

    class Nothing:  # a Zenoh session nobody listens to
        matching_status = type("Status", (), {"matching": False})()

        def declare_publisher(self, key: str) -> "Nothing":
            return self

        def put(self, payload: bytes, **kwargs: Any) -> None:
            pass

        def undeclare(self) -> None:
            pass

    relloc.cli.build_parser()  # every command module, as any command imports them
    assert compiled.ENABLED  # offline commands keep the compiled step
    sim, config = simulated_team(0, 4.0)
    server = LiveServer(config, Nothing())
    t0 = time.time() - 5.0
    for t, channel, payload in event_messages(sim.events(), config, time_base=t0):
        server.source.handle(channel.key, payload, t0 + t + 0.001)
    server.run(0.05)  # drains what is queued: the filter starts and steps
    assert compiled.ENABLED  # the serve's choice ended with its run
    print(server.summary()["methods"]["pf"]["estimates"])
    print(sorted({m.split(".")[0] for m in sys.modules} & {"numba", "llvmlite", "scipy"}))
    """
)


@pytest.mark.skipif(not compiled.AVAILABLE, reason="numba is not installed")
def test_the_serve_on_the_numpy_step_leaves_numba_and_scipy_unimported() -> None:
    env = {k: v for k, v in os.environ.items() if k != "RELLOC_COMPILED"}
    out = subprocess.run(
        [sys.executable, "-c", _SERVE], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    estimates, imported = out.stdout.split("\n")[:2]
    assert int(estimates) > 0
    assert imported == "[]"


def test_a_kernel_runs_as_written_while_the_compiled_step_is_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A :class:`~relloc.filter.compiled.LazyKernel` not yet compiled runs its Python function
    while :data:`~relloc.filter.compiled.ENABLED` is off, with the same result."""
    import numpy as np

    from relloc.filter.resampling import renormalize_into

    monkeypatch.setattr(compiled, "ENABLED", False)
    logw, w = np.log(np.array([1.0, 3.0])), np.empty(2)
    assert renormalize_into(logw, w)
    np.testing.assert_allclose(w, [0.25, 0.75])


def test_chosen_restores_the_switch() -> None:
    before = compiled.enabled()
    with compiled.chosen(False):
        assert not compiled.enabled()
    assert before == compiled.enabled()


def test_a_choice_stays_in_its_thread_and_ends_out_of_order_as_it_began() -> None:
    """Two servers of one process end in the other order than they began: neither's choice
    reaches the other thread, and the switch is as it was after both (it was left off, and an
    offline run afterwards, or a server's ``compiled=compiled.ENABLED``, took the other step)."""
    import threading

    before, seen = compiled.ENABLED, []
    entered, release = threading.Event(), threading.Event()

    def server() -> None:
        with compiled.chosen(False):
            seen.append(compiled.enabled())
            entered.set()
            release.wait(5.0)

    thread = threading.Thread(target=server)
    thread.start()
    assert entered.wait(5.0)
    with compiled.chosen(True):  # the second server begins, then the first one ends
        mine = compiled.enabled()
        assert before == compiled.ENABLED
        release.set()
        thread.join(5.0)
        assert compiled.enabled() == mine
    assert seen == [False] and before == compiled.ENABLED == compiled.enabled()


@pytest.mark.parametrize(
    ("flag", "expected"), [((), None), (("--compiled",), True), (("--no-compiled",), False)]
)
def test_serve_chooses_the_step_on_the_command_line(
    flag: tuple[str, ...], expected: bool | None
) -> None:
    """``--compiled``/``--no-compiled`` reach :attr:`ServeOptions.compiled`; neither: the
    default (NumPy unless ``RELLOC_COMPILED=1``)."""
    from relloc.cli import build_parser
    from relloc.cli.common import options_from_args
    from relloc.live.server import ServeOptions

    args = build_parser().parse_args(["serve", "--config", "team.toml", *flag])
    assert options_from_args(ServeOptions, args).compiled is expected
