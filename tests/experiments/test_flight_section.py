"""The report's flight section on the shared Betaflight log, and its firmware hook."""

from __future__ import annotations

from pathlib import Path

from experiments import flight
from experiments.report import ExperimentResult


def test_flight_section_on_the_unfiltered_log(shared_data, tmp_path):
    r = flight.run(out_dir=tmp_path, data_dir=str(shared_data), size="standard", find_binary=lambda: None)
    # (find_binary=None: the "not built" branch whatever this machine's firmware cache holds)
    s = r.summary
    # the log with the unfiltered gyro is picked (LOG00037: debug_mode 6 = GYRO_SCALED), not
    # better_tune.BBL (its debug is after a 90 Hz PT1)
    assert s["log"] == "blackbox_public/LOG00037.BFL" and s["signal"] == "raw"
    assert s["bands"] >= 2 and len(s["band_rms_above_40hz_deg_s"]) == s["bands"]
    # PROVENANCE.md: debug (GYRO_SCALED) 2.2/2.3/2.6 deg/s rms above 40 Hz over the whole log
    # (4th-order Butterworth); the airborne 1-s Hann windows give the same within 15 %
    for a, ref in zip("xyz", (2.2, 2.3, 2.6)):
        assert abs(s["rms_above_40hz_deg_s"][a] / ref - 1) < 0.15
    assert any(line.startswith("set gyro_lowpass") for line in s["betaflight_set"])
    assert "gyro_lowpass2_hz = 300" in s["flown_settings"]
    for f in r.figures:
        assert (tmp_path / f).stat().st_size > 1000
    assert "build it with `gyroharness firmware build`" in r.markdown
    assert s["firmware_in_the_loop"] == {"built": False}


def test_firmware_hook_calls_the_firmware_experiment_when_the_binary_is_built(tmp_path):
    class Binary:
        binary, version = "/cache/betaflight_SITL", "4.6.0"

    calls = []

    def fake_run(*, out_dir, binary, workers=None, **kw):
        calls.append((Path(out_dir), binary, kw))
        return ExperimentResult(
            name="cutoffs_firmware",
            title="Cutoffs flown by Betaflight",
            markdown="| grid |",
            figures=("figures/fw.png",),
            summary={"best": "pt1 90"},
        )

    md, figs, summ = flight.firmware_part(
        tmp_path, size="standard", find_binary=lambda: Binary(), firmware_run=fake_run
    )
    assert calls == [(tmp_path, "/cache/betaflight_SITL", flight.FIRMWARE_SIZES["standard"])]
    assert "| grid |" in md and "4.6.0" in md and figs == ("figures/fw.png",)
    assert summ["built"] and summ["cutoffs"] == {"best": "pt1 90"}
    # binary absent: one line naming the build command, nothing run
    md, figs, summ = flight.firmware_part(tmp_path, find_binary=lambda: None, firmware_run=fake_run)
    assert len(calls) == 1 and figs == () and "`gyroharness firmware build`" in md and "\n" not in md


def test_flight_section_without_data(tmp_path):
    r = flight.run(out_dir=tmp_path, data_dir=str(tmp_path / "none"), find_binary=lambda: None)
    assert "No flight log found" in r.markdown and r.figures == ()


def _fw_filter_out(seeds):
    """The shape of ``experiments.firmware_filter.run``'s JSON (two chains, as flown kept)."""
    stat = {"mean": 0.3, "sd": float("nan")}
    keys = ("attitude_cost_deg", "att_vibration_deg", "att_delay_deg", "att_delay_flight_deg", "motor_noise_pct")
    keys += ("dterm_noise", "delay_ms", "rise_ms", "overshoot_pct")
    chain = {k: stat for k in keys}
    pub = {"name": "as_flown", "set": [], "attitude_cost": 0.3, "motor_noise": 1.5, "delay_ms": 3.0}
    return {
        "firmware": "betaflight 4.6.0",
        "vehicle": "racing25",
        "band": "middle",
        "tune": ["set gyro_lowpass_hz = 90"],
        "seeds": list(seeds),
        "chains": {
            "as_flown": {**chain, "lines": []},
            "pt1 60 Hz": {**chain, "lines": ["set gyro_lpf1_static_hz = 60"]},
        },
        "picks_per_seed": ["as_flown"] * len(seeds),
        "stable": True,
        "recommended": pub,
        "as_flown": pub,
        "firmware_lines": {"betaflight": ["# keep the tune as flown"]},
    }


def test_firmware_filter_part_flies_the_tune_at_the_research_size_only(shared_data, tmp_path):
    class Binary:
        binary, version = "/cache/betaflight_SITL", "4.6.0"

    calls = []

    def fake_run(*, flight, binary, workers, seeds, duration_s):
        calls.append((flight, binary, seeds, duration_s))
        return _fw_filter_out(seeds)

    # the default report names the command instead of flying it (its flights cost minutes of CPU)
    md, summ = flight.firmware_filter_part(
        shared_data, size="standard", find_binary=lambda: Binary(), filter_run=fake_run
    )
    assert calls == [] and not summ["run"] and "--firmware betaflight" in md and "--full" in md
    # --full flies the pilot's tune and the candidates on better_tune.BBL with the firmware
    md, summ = flight.firmware_filter_part(shared_data, size="full", find_binary=lambda: Binary(), filter_run=fake_run)
    opts = flight.FIRMWARE_FILTER_SIZES["full"]
    assert calls == [
        (str(shared_data / flight.FIRMWARE_FILTER_LOG), "/cache/betaflight_SITL", opts["seeds"], opts["duration_s"])
    ]
    assert summ["run"] and summ["recommended"]["name"] == "as_flown" and summ["firmware"] == "betaflight 4.6.0"
    assert "| pt1 60 Hz | gyro_lpf1_static_hz = 60 |" in md and "recommended: as_flown" in md
    # no binary: one line naming the build command, nothing flown
    md, summ = flight.firmware_filter_part(shared_data, size="full", find_binary=lambda: None, filter_run=fake_run)
    assert len(calls) == 1 and not summ["run"] and "`gyroharness firmware build`" in md and "\n" not in md
    # no log: says which one is missing
    md, summ = flight.firmware_filter_part(tmp_path, size="full", find_binary=lambda: Binary(), filter_run=fake_run)
    assert len(calls) == 1 and not summ["run"] and flight.FIRMWARE_FILTER_LOG in md
