"""Live's deferred least-squares decoding (``LocaliserConfig.defer_lsq``): what a deferred decode read
is taken by the next frame only where that frame's view confirms it, and a replay is unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tagloc.core.camera import default_camera
from tagloc.core.geometry import make_T
from tagloc.core.rig import Rig, RigCamera
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import Frame, Identity, IdSource
from tagloc.eval.evaluate import wrong_id_fixes
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import DeferredRead, Localiser, LocaliserConfig
from tagloc.pipeline.run import run_session
from tagloc.sim.mapgen import GridMapConfig, grid_map
from tagloc.sim.simulate import SimConfig, simulate_session
from tests.synth import floor_view, synth_frame

STICKER, OTHER = 12345, 12346  # same decade: they differ in the last codeword only


def _scene():
    """One sharp sticker 1.2 m ahead of a camera pitched 55 deg down, its map, rig and frame."""
    cam = default_camera()
    T_wc = floor_view(cam)
    T_ws = make_T(np.eye(3), (1.2, 0.0, 0.0))
    smap = StickerMap(np.array([STICKER, OTHER]), np.array([[1.2, 0.0], [5.0, 5.0]]), np.zeros(2))
    # The rig camera's pose on the body: the body sits at the world origin, unrotated.
    rig = Rig([RigCamera("front", cam, T_wc)])
    frame = synth_frame([(STICKER, T_ws)], cam, T_wc, gamma=2.2, seed=3)
    return smap, rig, frame


@pytest.mark.parametrize("sid, taken", [(STICKER, True), (OTHER, False)])
def test_a_deferred_read_is_taken_only_where_the_modules_confirm_it(sid, taken):
    smap, rig, frame = _scene()
    loc = Localiser(smap, rig, LocaliserConfig(defer_lsq=True, odometry=False))
    outer = frame.outer[0]
    # The previous frame's deferred decode read ``sid`` (canonical corner first) 20 px to the left.
    loc._deferred = [DeferredRead(outer - [20.0, 0.0], Identity(sid, 0, IdSource.DECODED), 0, 0.0)]
    res = loc.process(Frame(1, 1 / 30, frame.image))
    (obs,) = res.observations
    assert loc.counts["deferred_reads"] == int(taken)
    if taken:
        assert obs.identity.sticker_id == STICKER and obs.identity.source is IdSource.DECODED
        np.testing.assert_allclose(obs.detection.outer[obs.identity.rotation], outer[0], atol=2.0)
    # A wrong deferred ID is never taken: the sticker is decoded as usual (zxing reads this sharp one).
    assert obs.identity is None or obs.identity.sticker_id == STICKER


def test_deferred_reads_last_one_frame_and_a_replay_defers_nothing():
    smap, rig, frame = _scene()
    loc = Localiser(smap, rig, LocaliserConfig(defer_lsq=True, odometry=False))
    loc._deferred = [DeferredRead(frame.outer[0], Identity(STICKER, 0, IdSource.DECODED), 0, 0.0)]
    loc.process(Frame(1, 1.0, frame.image))  # a second later: past ``max_gap_s``
    assert loc.counts["deferred_reads"] == 0 and loc._deferred == []
    replay = Localiser(smap, rig, LocaliserConfig(odometry=False))
    replay.process(Frame(0, 0.0, frame.image))
    assert replay.deferred_work() == 0 and replay.counts["lsq_deferred"] == 0


@pytest.fixture(scope="module")
def blurred_walk(tmp_path_factory) -> Path:
    """A 6 s walk at 60 lux: long exposures blur stickers enough that some need least squares."""
    path = tmp_path_factory.mktemp("defer") / "walk"
    smap = grid_map(GridMapConfig(width_m=12, depth_m=10, spacing_min_m=1.2, spacing_max_m=1.6, seed=5))
    simulate_session(smap, path, SimConfig(seconds=6, lux=60, speed_mps=1.4, seed=4), progress=False)
    return path


class _AsLive:
    """The localiser as the live loop drives it: the deferred work right after each frame."""

    def __init__(self, loc: Localiser):
        self.loc, self.map, self.rig, self.counts = loc, loc.map, loc.rig, loc.counts

    def process(self, frame):
        res = self.loc.process(frame)
        self.loc.deferred_work()
        return res

    def stats(self):
        return self.loc.stats()


def test_deferred_decodes_name_stickers_one_frame_later_and_never_wrongly(blurred_walk):
    session = SessionReader(blurred_walk)
    replay = run_session(session, LocaliserConfig())
    loc = Localiser(session.map, session.rig, LocaliserConfig(defer_lsq=True), map_path=session.map_path)
    live = run_session(SessionReader(blurred_walk), localiser=_AsLive(loc))
    assert loc.counts["lsq_deferred"] >= 3  # the walk has stickers that need least squares
    assert loc.counts["deferred_reads"] >= 1
    assert wrong_id_fixes(blurred_walk, live)[0] == 0 and wrong_id_fixes(blurred_walk, replay)[0] == 0
    # Each deferred decode costs at most its own frame's fix (and identification there).
    assert len(live.fixes) >= len(replay.fixes) - 2 * loc.counts["lsq_deferred"]
