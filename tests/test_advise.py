"""tagloc advise: the exposure trade-off measured on the simulator's frames."""

from __future__ import annotations

import pytest

from tagloc.cli import main
from tagloc.core.errors import InputError
from tagloc.eval.advise import AdviseConfig, AdviseRow, advise, best_row, format_advice


def test_trade_off_follows_the_physics():
    cfg = AdviseConfig(lux=100.0, speed_mps=1.3, exposures_ms=(1.0, 4.0), frames=4, scale=0.5, seed=3)
    short, long_ = advise(cfg, progress=False)
    # Blur grows in proportion to the exposure (same views, same speed); SNR grows with the light.
    assert long_.blur_px / short.blur_px == pytest.approx(4.0, rel=0.05)
    assert long_.snr > 1.8 * short.snr
    # At 100 lux the Pi sensor's gain is capped at 1 ms: the image is darker than the AE target.
    assert short.gain == pytest.approx(32.0) and short.brightness < 0.5
    assert short.stickers == long_.stickers > 0
    for r in (short, long_):
        assert 0 <= r.read <= r.identified <= r.detected <= 1 and r.wrong == 0
    assert long_.identified > short.identified
    assert best_row([short, long_]) is long_
    assert "recommended: --exposure-ms 4" in format_advice([short, long_], cfg)


def test_bad_settings():
    with pytest.raises(InputError):
        AdviseConfig(exposures_ms=(0.0,))
    with pytest.raises(InputError):
        AdviseConfig(lux=0)
    assert main(["advise", "--lux", "-5"]) == 2


def test_no_recommendation_when_no_exposure_gives_a_fix(capsys):
    """At 5 lux no exposure up to 1 ms gives a fix: the tie at 0 % went to the shortest, and the
    command recommended "--exposure-ms 0.5: 0% of stickers in view give a fix" and exited 0. Now it
    prints the table, says there is no recommendation and what would help, and exits 1."""
    args = ["advise", "--lux", "5", "--frames", "2", "--scale", "0.5", "--exposures", "0.5", "1", "--no-progress"]
    assert main(args) == 1
    out = capsys.readouterr().out
    assert "recommended" not in out and "0.50ms" in out and "1.00ms" in out
    assert out.rstrip().endswith(
        "no recommendation: no exposure tried (up to 1 ms) gives a fix; more light, a slower walk or longer --exposures"
    )
    cfg = AdviseConfig(exposures_ms=(0.5, 1.0))
    rows = [AdviseRow(e, 32.0, 1.0, 1.0, 0.1, 10, 0.0, 0.0, 0.0, 0.0) for e in cfg.exposures_ms]
    assert best_row(rows) is None
    rows[1].identified = 0.1
    assert best_row(rows) is rows[1] and "recommended: --exposure-ms 1 " in format_advice(rows, cfg)


def test_an_exposure_that_gave_a_wrong_id_is_never_recommended():
    """More fixes never buy a wrong sticker ID: the exposure with the most fixes among those without
    one is recommended, and none when every exposure with fixes gave a wrong ID."""
    cfg = AdviseConfig(exposures_ms=(1.0, 2.0, 4.0))
    rows = [
        AdviseRow(1.0, 8.0, 1.0, 5.0, 0.9, 10, 0.9, 0.5, 0.6, 0.0),
        AdviseRow(2.0, 4.0, 2.0, 7.0, 0.9, 10, 0.9, 0.7, 0.8, 0.0),
        AdviseRow(4.0, 2.0, 4.0, 9.0, 0.9, 10, 0.9, 0.8, 0.9, 0.1),
    ]
    assert best_row(rows) is rows[1]
    assert "recommended: --exposure-ms 2 " in format_advice(rows, cfg)
    for r in rows[:2]:
        r.wrong = 0.05
    assert best_row(rows) is None
    assert "every exposure that gives a fix also gave a wrong sticker ID" in format_advice(rows, cfg)
