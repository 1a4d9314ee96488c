"""Fidelity of the simulated hover's gyro vibration against a real flight's.

For each throttle band of a vibration spec (``gyroharness vibration FLIGHT -o spec.json``):
the in-band fraction (:func:`gyrocore.flight.synthesis.fidelity`: bins 40 Hz .. the spec's reliable
limit where the simulated gyro PSD is statistically indistinguishable from the real band's;
0.95 expected for a perfect match) of

* *before*: the simulated hover as it is (today's F450 vibration, physics only), and
* *after*: the same simulation (re-run from the recording's metadata) with the band's measured
  PSD as the registry effect ``vibration``'s shaped part (a hover's controller flies on it); a
  recording that is not a simulation's gets it open loop (:func:`gyrocore.flight.synthesis.add_vibration`).

With ``--vehicle racing5`` two more columns per band, from a closed-loop hover of that vehicle
class (``--vehicle-duration-s``, airborne start, analysed after 2 s):

* *physics*: the spec band's rotor line entered through the rotor imbalance
  (:func:`sim.spec_vibration.vibration_from_spec`), at the class's commanded rotor frequency;
* *physics + shaped*: plus the band's PSD without the real rotor line (± max(3 bins, 6 %)) as
  the shaped disturbance — what ``gyroharness simulate hover --vehicle racing5 --vibration SPEC
  --vibration-physics --vibration-band i`` writes.

    python -m experiments.vibration_fidelity --spec spec.json --hover hover.csv [--t-from-s 8] [--seed 0]
        [--vehicle racing5 [--vehicle-duration-s 12] [--plot fidelity.png]]

Out of sample (``--flight``): the spec is built from the first half of the flight (``analyse(t <
t_mid)``, its 8 equal-count throttle bands) and the simulated hovers are compared with the
second half analysed in the same bands (``band_edges``); the in-sample figure (the same hovers
against the first half) is printed second. Columns: *before* = today's F450 defaults (no spec);
*after* = the vehicle class (default ``racing25``, the log's quad) with the first half's band in
the physics (its rotor line through the static + hub-moment unbalance) and the rest of the band as
the registry effect ``vibration``'s shaped part — what ``gyroharness simulate hover --vehicle
racing25 --vibration SPEC_A --vibration-physics --vibration-band i`` writes.

    python -m experiments.vibration_fidelity --flight FLIGHT.BBL [--vehicle racing25] [--out-dir d] [--plot p.png]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
from gyrocore.data.recording import atomic_write_bytes, read_csv
from gyrocore.errors import GyroInputError
from gyrocore.flight.synthesis import add_vibration, fidelity, shaped_params
from gyrocore.flight.vibration import analyse, read_spec, write_spec
from gyrocore.readers.convert import detect_format, load_any
from sim import scenarios as S
from sim.spec_vibration import spec_injection


def _vehicle_hover(spec: dict, band: int, *, vehicle: str, duration_s: float, seed: int):
    """(physics-only recording, physics + shaped recording) of one band, as ``simulate --vibration-physics``
    (both through :func:`sim.spec_vibration.spec_injection`, the registry effect ``vibration``)."""
    hv, over, info = spec_injection(spec, band=band, vehicle=vehicle, physics=True, seed=seed)
    phys = S.simulate("hover", duration_s=duration_s, seed=seed, vehicle=vehicle, hover_vibration=hv).recording
    shaped = S.simulate(
        "hover", duration_s=duration_s, seed=seed, vehicle=vehicle, hover_vibration=hv, overrides=over
    ).recording
    return phys, shaped, info["physics"]


def _with_spec_band(rec, spec: dict, band: int, *, seed: int):
    """``rec`` again with the spec band's shaped part, the way every effect enters: re-simulated from
    its own metadata (scenario, sensor, seed, run, duration, vehicle) with the registry effect
    ``vibration`` switched on. A recording that is not a simulation's is given the disturbance
    open loop (:func:`gyrocore.flight.synthesis.add_vibration`), said in the returned note."""
    m = rec.meta
    try:
        res = S.simulate(
            m["scenario"],
            sensor=m.get("sensor", "icm42688p"),
            duration_s=float(m["duration_s"]),
            seed=int(m["seed"]),
            run=int(m.get("run", 0)),
            gyro_rate_hz=float(m["rate_hz"]),
            vehicle=m.get("vehicle") if m.get("vehicle") else None,
            overrides={"vibration": shaped_params(spec, band=band)},
        )
        return res.recording, "registry effect vibration (re-simulated from the recording's metadata)"
    except (KeyError, ValueError, GyroInputError):
        return (
            add_vibration(rec, spec, seed=int(np.random.SeedSequence([seed, band]).generate_state(1)[0]), band=band),
            "open loop (add_vibration: not a simulated recording)",
        )


def run(
    *,
    spec_path: str,
    hover_path: str,
    t_from_s: float = 8.0,
    seed: int = 0,
    vehicle: str | None = None,
    vehicle_duration_s: float = 12.0,
    plot: str | None = None,
    plot_bands=(0, 4, 7),
) -> dict:
    """Table rows per band: in-band fraction and rms above 40 Hz, before and after (and the vehicle class's)."""
    spec = read_spec(spec_path)
    hover = read_csv(hover_path)
    before = analyse(hover, t_from_s=t_from_s)
    rows = []
    curves = {}
    for i, b in enumerate(spec["bands"]):
        after_rec, how = _with_spec_band(hover, spec, i, seed=seed)
        after = analyse(after_rec, t_from_s=t_from_s)
        fb, fa = fidelity(before, spec, band=i), fidelity(after, spec, band=i)
        row = {"band": i, "throttle": b["throttle"], "median": b["median"], "before": fb, "after": fa, "after_how": how}
        if vehicle:
            phys, shaped, info = _vehicle_hover(spec, i, vehicle=vehicle, duration_s=vehicle_duration_s, seed=seed)
            a_ph, a_ps = analyse(phys, t_from_s=2.0), analyse(shaped, t_from_s=2.0)
            row["physics"] = fidelity(a_ph, spec, band=i)
            row["physics_shaped"] = fidelity(a_ps, spec, band=i)
            if plot and i in plot_bands:
                curves[i] = {
                    "F450 defaults": before,
                    f"{vehicle} + spec physics": a_ph,
                    f"{vehicle} + physics + shaped": a_ps,
                }
            row["physics_info"] = info
        rows.append(row)
    if plot and curves:
        _plot(spec, curves, plot)
    return {"spec": spec_path, "hover": hover_path, "t_from_s": t_from_s, "vehicle": vehicle, "rows": rows}


def _plot(spec: dict, curves: dict, path: str) -> None:
    """Gyro PSD per plotted band (rows) and axis x, z (columns): real band vs the simulated ones."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d2 = (180 / math.pi) ** 2
    f_r = np.asarray(spec["f_hz"], float)
    lim = float(spec.get("reconstructed_reliable_below_hz") or f_r[-1])
    bands = sorted(curves)
    fig, axs = plt.subplots(len(bands), 2, figsize=(11, 3.2 * len(bands)), squeeze=False)
    for r, i in enumerate(bands):
        b = spec["bands"][i]
        for c, ax_name in enumerate("xz"):
            ax = axs[r, c]
            real = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][ax_name]], float)
            ax.semilogy(f_r, real * d2, "k", lw=1.6, label="real flight (2.5-inch, before firmware filters)")
            _finish_psd_axis(
                ax,
                curves[i],
                ax_name,
                f_r,
                lim,
                title=f"band {i} (motor cmd {b['throttle'][0]:.2f}-{b['throttle'][1]:.2f}), gyro {ax_name}",
                xlabel="frequency, Hz (grey: above the spec's reliable limit)" if r == len(bands) - 1 else None,
            )
    _save_png(fig, axs, path)


def _finish_psd_axis(
    ax,
    sims: dict,
    ax_name: str,
    f_r: np.ndarray,
    lim: float,
    *,
    title: str,
    xlabel: str | None,
    title_fontsize: float | None = None,
) -> None:
    """One PSD panel of the fidelity plots: the simulated curves ((°/s)²/Hz), the band above the
    spec's reliable limit greyed, title and labels."""
    d2 = (180 / math.pi) ** 2
    for name, res in sims.items():
        ax.semilogy(res.f_hz, res.mean_psd[:, "xyz".index(ax_name)] * d2, lw=0.9, label=name)
    ax.axvspan(lim, f_r[-1], color="0.9")
    ax.set_xlim(0, f_r[-1])
    ax.set_title(title, **({} if title_fontsize is None else {"fontsize": title_fontsize}))
    ax.set_ylabel("PSD, (°/s)²/Hz")
    if xlabel:
        ax.set_xlabel(xlabel)


def _save_png(fig, axs, path: str) -> None:
    """Legend on the first panel, then the figure as a PNG written atomically."""
    import io

    import matplotlib.pyplot as plt

    axs[0, 0].legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=70)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=None)
    ap.add_argument("--hover", default=None)
    ap.add_argument(
        "--flight", default=None, help="out of sample: spec from the first half of this flight, compared on the second"
    )
    ap.add_argument("--out-dir", default=None, help="--flight: where the two half specs are written")
    ap.add_argument("--duration-s", type=float, default=12.0, help="--flight: hover length, s")
    ap.add_argument("--t-from-s", type=float, default=8.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vehicle", default=None, help="also fly this vehicle class with the spec (e.g. racing5)")
    ap.add_argument("--vehicle-duration-s", type=float, default=12.0)
    ap.add_argument("--plot", default=None, help="PNG of the PSDs of bands 0, 4, 7 (with --vehicle)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    if a.flight:
        out = run_split(
            flight=a.flight,
            vehicle=a.vehicle or "racing25",
            seed=a.seed,
            duration_s=a.duration_s,
            out_dir=a.out_dir,
            plot=a.plot,
        )
        if a.json:
            print(json.dumps(out, indent=1, default=str))
        else:
            _print_split(out)
        return
    if not (a.spec and a.hover):
        ap.error("give --flight, or --spec and --hover")
    out = run(
        spec_path=a.spec,
        hover_path=a.hover,
        t_from_s=a.t_from_s,
        seed=a.seed,
        vehicle=a.vehicle,
        vehicle_duration_s=a.vehicle_duration_s,
        plot=a.plot,
    )
    if a.json:
        print(json.dumps(out, indent=1))
        return
    d = 180 / math.pi
    if a.vehicle:
        v = a.vehicle
        print(
            f"| band (motor cmd) | axis | in-band: F450 defaults | F450 + shaped (open loop) | {v} + spec physics | "
            f"{v} + physics + shaped | rms >40 Hz, deg/s: F450 / {v} physics / {v} physics+shaped / real |"
        )
        print("|---|---|---|---|---|---|---|")
    else:
        print(
            "| band (motor cmd) | axis | in-band before | in-band after | rms >40 Hz sim before / after / real, deg/s |"
        )
        print("|---|---|---|---|---|")
    for r in out["rows"]:
        for ax in "xyz":
            b, af = r["before"][ax], r["after"][ax]
            if a.vehicle:
                ph, ps = r["physics"][ax], r["physics_shaped"][ax]
                print(
                    f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | "
                    f"{af['in_band_fraction']:.2f} | {ph['in_band_fraction']:.2f} | {ps['in_band_fraction']:.2f} | "
                    f"{b['rms_sim_rad_s'] * d:.2f} / {ph['rms_sim_rad_s'] * d:.2f} / {ps['rms_sim_rad_s'] * d:.2f} / "
                    f"{b['rms_real_rad_s'] * d:.2f} |"
                )
            else:
                print(
                    f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | {af['in_band_fraction']:.2f} | "
                    f"{b['rms_sim_rad_s'] * d:.2f} / {af['rms_sim_rad_s'] * d:.2f} / {b['rms_real_rad_s'] * d:.2f} |"
                )


# ---------------------------------------------------------------------------- out of sample
def _hover_result(
    spec, band, *, vehicle: str, duration_s: float, seed: int, n_calib: int, calib_s: float, t_from_s: float
):
    """Analysis of a hover of ``vehicle`` with the spec band injected (physics + registry shaped part)."""
    hv, over, info = spec_injection(
        spec, band=band, vehicle=vehicle, physics=True, seed=seed, n_calib=n_calib, calib_s=calib_s
    )
    res = S.simulate("hover", duration_s=duration_s, seed=seed, vehicle=vehicle, overrides=over, hover_vibration=hv)
    return analyse(res.recording, t_from_s=t_from_s), info


def run_split(
    *,
    flight: str,
    vehicle: str = "racing25",
    seed: int = 0,
    duration_s: float = 12.0,
    t_from_s: float = 2.0,
    n_calib: int = 16,
    calib_s: float = 2.0,
    out_dir: str | None = None,
    plot: str | None = None,
    plot_bands=(0, 3, 7),
) -> dict:
    """Fidelity per throttle band, out of sample (spec from the first half, compared on the second).

    Returns ``{"t_split_s", "bands": [{"band", "throttle", "out_of_sample": {"before": fid, "after": fid},
    "in_sample": {...}, "physics": info}]}`` with ``fid`` = :func:`gyrocore.flight.synthesis.fidelity` per axis.
    """
    import os
    import tempfile
    from types import SimpleNamespace

    rec = read_csv(flight) if detect_format(flight) == "csv" else load_any(flight)
    t = rec.t_s
    t_mid = float(t[0] + 0.5 * (t[-1] - t[0]))
    res_a = analyse(rec, t_to_s=t_mid)
    edges = [b["throttle"][0] for b in res_a.bands] + [res_a.bands[-1]["throttle"][1]]
    res_b = analyse(rec, t_from_s=t_mid, band_edges=edges)
    d = out_dir or tempfile.mkdtemp(prefix="vibfid_")
    os.makedirs(d, exist_ok=True)
    spec_a = write_spec(res_a, os.path.join(d, "spec_first_half.json"), source=f"{flight} t < {t_mid:.2f} s")
    spec_b = write_spec(res_b, os.path.join(d, "spec_second_half.json"), source=f"{flight} t >= {t_mid:.2f} s")
    b_index = {round(b["throttle"][0], 9): j for j, b in enumerate(spec_b["bands"])}
    f450 = S.simulate("hover", duration_s=duration_s, seed=seed, vehicle="f450")
    before = analyse(f450.recording, t_from_s=t_from_s)
    rows, curves = [], {}
    for i, b in enumerate(spec_a["bands"]):
        j = b_index.get(round(b["throttle"][0], 9))
        if j is None:
            continue  # the second half has too few windows in this band
        after, info = _hover_result(
            spec_a,
            i,
            vehicle=vehicle,
            duration_s=duration_s,
            seed=seed,
            n_calib=n_calib,
            calib_s=calib_s,
            t_from_s=t_from_s,
        )
        # the data's own repeatability: the first half's band against the second half's, same test
        half_a = SimpleNamespace(
            f_hz=np.asarray(spec_a["f_hz"], float),
            n_windows=int(b["n_windows"]),
            mean_psd=np.column_stack([[np.nan if x is None else x for x in b["psd_rad2_s2_hz"][a]] for a in "xyz"]),
        )
        rows.append(
            {
                "band": i,
                "throttle": b["throttle"],
                "n_windows_first": b["n_windows"],
                "first_vs_second_half": fidelity(half_a, spec_b, band=j),
                "n_windows_second": spec_b["bands"][j]["n_windows"],
                "out_of_sample": {"before": fidelity(before, spec_b, band=j), "after": fidelity(after, spec_b, band=j)},
                "in_sample": {"before": fidelity(before, spec_a, band=i), "after": fidelity(after, spec_a, band=i)},
                "physics": info.get("physics"),
            }
        )
        if plot and i in plot_bands:
            curves[i] = (j, {"F450 defaults": before, f"{vehicle}, first-half spec (physics + shaped)": after})
    if plot and curves:
        _plot_split(spec_a, spec_b, curves, plot)
    return {
        "flight": flight,
        "t_split_s": t_mid,
        "vehicle": vehicle,
        "seed": seed,
        "duration_s": duration_s,
        "spec_first_half": os.path.join(d, "spec_first_half.json"),
        "spec_second_half": os.path.join(d, "spec_second_half.json"),
        "bands": rows,
    }


def _plot_split(spec_a: dict, spec_b: dict, curves: dict, path: str) -> None:
    """PSD per plotted band (rows) and axis x, y, z: second half (held out), first half, the simulations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d2 = (180 / math.pi) ** 2
    f_r = np.asarray(spec_a["f_hz"], float)
    lim = float(spec_a.get("reconstructed_reliable_below_hz") or f_r[-1])
    bands = sorted(curves)
    fig, axs = plt.subplots(len(bands), 3, figsize=(14, 3.2 * len(bands)), squeeze=False)
    for r, i in enumerate(bands):
        j, sims = curves[i]
        ba, bb = spec_a["bands"][i], spec_b["bands"][j]
        for c, ax_name in enumerate("xyz"):
            ax = axs[r, c]
            for b, lab, sty in ((bb, "real, second half (held out)", "k"), (ba, "real, first half (spec)", "0.6")):
                v = np.array([np.nan if x is None else x for x in b["psd_rad2_s2_hz"][ax_name]], float)
                ax.semilogy(f_r, v * d2, sty, lw=1.4, label=lab)
            _finish_psd_axis(
                ax,
                sims,
                ax_name,
                f_r,
                lim,
                title_fontsize=9,
                title=f"band {i} (motor cmd {ba['throttle'][0]:.2f}-{ba['throttle'][1]:.2f}), gyro {ax_name}",
                xlabel="Hz (grey: above the spec's reliable limit)" if r == len(bands) - 1 else None,
            )
    _save_png(fig, axs, path)


def _print_split(out: dict) -> None:
    d = 180 / math.pi
    v = out["vehicle"]
    for which in ("out_of_sample", "in_sample"):
        title = (
            "OUT OF SAMPLE: spec from t < %.1f s, compared with the second half" % out["t_split_s"]
            if which == "out_of_sample"
            else "IN SAMPLE: the same hovers against the first half (the spec's own data)"
        )
        print(title)
        oos = which == "out_of_sample"
        print(
            f"| band (motor cmd) | axis | in-band: F450 defaults | in-band: {v} + spec |"
            + (" real first half vs second half |" if oos else "")
            + f" rms >40 Hz, deg/s: F450 / {v} / real |"
        )
        print("|---|---|---|---|" + ("---|" if oos else "") + "---|")
        for r in out["bands"]:
            for ax in "xyz":
                b, a = r[which]["before"][ax], r[which]["after"][ax]
                print(
                    f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | "
                    f"{a['in_band_fraction']:.2f} |"
                    + (f" {r['first_vs_second_half'][ax]['in_band_fraction']:.2f} |" if oos else "")
                    + f" {b['rms_sim_rad_s'] * d:.2f} / {a['rms_sim_rad_s'] * d:.2f} / {b['rms_real_rad_s'] * d:.2f} |"
                )
        fr = [r[which]["after"][ax]["in_band_fraction"] for r in out["bands"] for ax in "xyz"]
        fb = [r[which]["before"][ax]["in_band_fraction"] for r in out["bands"] for ax in "xyz"]
        print(
            f"in-band fraction, median over bands and axes: before {np.median(fb):.2f}, after {np.median(fr):.2f} "
            f"(range {min(fr):.2f}-{max(fr):.2f})"
            + (
                f"; real first half vs second half {np.median([r['first_vs_second_half'][ax]['in_band_fraction'] for r in out['bands'] for ax in 'xyz']):.2f}"
                if oos
                else ""
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
