"""The firmware soak (tests/firmware/soak.py): strokes in simavr through the MCU protocol, every
start, depart and arrive stamp and every drive-off against the harness's truth.

`make test` runs a short one (2,000 strokes, ~2 s). `make soak` runs 100,000 strokes
(USMSWITCH_SOAK_STROKES) and then shows the soak finding a planted one-period stamp error: the
test image with the stamp computation of before issue 23 (USMSWITCH_PLANT_STAMP_ERROR) must fail
it (USMSWITCH_SOAK_PLANT=1).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import BUILD, make
from soak import run_soak

STROKES = int(os.environ.get("USMSWITCH_SOAK_STROKES", "2000"))


@pytest.mark.timeout(3600)
def test_soak_every_stamp_equals_the_truth(avrsim: Path, firmware_elf: Path, tmp_path: Path) -> None:
    res = run_soak(avrsim, firmware_elf, STROKES, tmp_path)
    print(res.summary())
    detail = f"\nwrong {res.wrong[:10]}, slow cuts {res.slow_cuts[:10]}, missing {res.missing}"
    assert res.ok, res.summary() + detail
    assert res.strokes == STROKES
    assert res.near_overflow >= STROKES // 100  # the aim works: arrivals at the overflow by the hundred
    assert max(res.worst_us.values()) <= 1 and res.worst_cut_ns < 5000


PLANT = os.environ.get("USMSWITCH_SOAK_PLANT") == "1"


@pytest.mark.timeout(3600)
@pytest.mark.skipif(not PLANT, reason="make soak runs it: USMSWITCH_SOAK_PLANT=1")
def test_soak_finds_a_planted_one_period_stamp_error(avrsim: Path, tmp_path: Path) -> None:
    make("build/usmswitch-plant.elf")
    res = run_soak(avrsim, BUILD / "usmswitch-plant.elf", 100_000, tmp_path, max_wrong=2)
    print(res.summary())
    assert res.wrong, "the soak passed the firmware with the old stamp computation"
    assert all((fw - tr) % (1 << 32) == 32768 for _, _, fw, tr in res.wrong), res.wrong
