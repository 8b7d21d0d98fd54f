"""tagloc advise: the exposure trade-off measured on the simulator's frames."""

from __future__ import annotations

import pytest

from tagloc.cli import main
from tagloc.core.errors import InputError
from tagloc.eval.advise import AdviseConfig, advise, best_row, format_advice


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
