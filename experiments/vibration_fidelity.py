"""Fidelity of the simulated hover's gyro vibration against a real flight's (issue 16 item 3).

For each throttle band of a vibration spec (``gyroharness vibration FLIGHT -o spec.json``):
the in-band fraction (:func:`gyrocore.vibration.fidelity`: bins 40 Hz .. the spec's reliable
limit where the simulated gyro PSD is statistically indistinguishable from the real band's;
0.95 expected for a perfect match) of

* *before*: the simulated hover as it is (today's F450 vibration, physics only), and
* *after*: the same recording with the band's measured PSD added as a shaped disturbance
  (:func:`gyrocore.vibration.add_vibration`, open loop).

With ``--vehicle racing5`` two more columns per band, from a closed-loop hover of that vehicle
class (``--vehicle-duration-s``, airborne start, analysed after 2 s):

* *physics*: the spec band's rotor line entered through the rotor imbalance
  (:func:`sim.spec_vibration.vibration_from_spec`), at the class's commanded rotor frequency;
* *physics + shaped*: plus the band's PSD without the real rotor line (± max(3 bins, 6 %)) as
  the shaped disturbance — what ``gyroharness simulate hover --vehicle racing5 --vibration SPEC
  --vibration-physics --vibration-band i`` writes.

    python -m experiments.vibration_fidelity --spec spec.json --hover hover.csv [--t-from-s 8] [--seed 0]
        [--vehicle racing5 [--vehicle-duration-s 12] [--plot fidelity.png]]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np


def _vehicle_hover(spec: dict, band: int, *, vehicle: str, duration_s: float, seed: int):
    """(physics-only recording, physics + shaped recording) of one band, as ``simulate --vibration-physics``."""
    from gyrocore.vibration import add_vibration
    from sim import scenarios as S
    from sim.spec_vibration import vibration_from_spec

    v, info = vibration_from_spec(spec, vehicle, band=band, seed=seed)
    res = S.simulate("hover", duration_s=duration_s, seed=seed, vehicle=vehicle, hover_vibration=v)
    f_line = info["real_line_hz"]
    df = float(spec["f_hz"][1]) - float(spec["f_hz"][0])
    half = max(3 * df, 0.06 * f_line)
    rec = res.recording
    shaped = add_vibration(rec, spec, seed=int(np.random.SeedSequence([seed, 0, 16]).generate_state(1)[0]), band=band,
                           exclude_hz=((f_line - half, f_line + half),))
    return rec, shaped, info


def run(*, spec_path: str, hover_path: str, t_from_s: float = 8.0, seed: int = 0, vehicle: str | None = None,
        vehicle_duration_s: float = 12.0, plot: str | None = None, plot_bands=(0, 4, 7)) -> dict:
    """Table rows per band: in-band fraction and rms above 40 Hz, before and after (and the vehicle class's)."""
    from gyrocore.recording import read_csv
    from gyrocore.vibration import add_vibration, analyse, fidelity, read_spec

    spec = read_spec(spec_path)
    hover = read_csv(hover_path)
    before = analyse(hover, t_from_s=t_from_s)
    rows = []
    curves = {}
    for i, b in enumerate(spec["bands"]):
        after_rec = add_vibration(hover, spec, seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]), band=i)
        after = analyse(after_rec, t_from_s=t_from_s)
        fb, fa = fidelity(before, spec, band=i), fidelity(after, spec, band=i)
        row = {"band": i, "throttle": b["throttle"], "median": b["median"], "before": fb, "after": fa}
        if vehicle:
            phys, shaped, info = _vehicle_hover(spec, i, vehicle=vehicle, duration_s=vehicle_duration_s, seed=seed)
            a_ph, a_ps = analyse(phys, t_from_s=2.0), analyse(shaped, t_from_s=2.0)
            row["physics"] = fidelity(a_ph, spec, band=i)
            row["physics_shaped"] = fidelity(a_ps, spec, band=i)
            if plot and i in plot_bands:
                curves[i] = {"F450 defaults": before, f"{vehicle} + spec physics": a_ph, f"{vehicle} + physics + shaped": a_ps}
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

    from gyrocore.recording import atomic_write_bytes

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
            for name, res in curves[i].items():
                ax.semilogy(res.f_hz, res.mean_psd[:, "xyz".index(ax_name)] * d2, lw=0.9, label=name)
            ax.axvspan(lim, f_r[-1], color="0.9")
            ax.set_xlim(0, f_r[-1])
            ax.set_title(f"band {i} (motor cmd {b['throttle'][0]:.2f}-{b['throttle'][1]:.2f}), gyro {ax_name}")
            ax.set_ylabel("PSD, (°/s)²/Hz")
            if r == len(bands) - 1:
                ax.set_xlabel("frequency, Hz (grey: above the spec's reliable limit)")
    axs[0, 0].legend(fontsize=7)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=70)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", required=True)
    ap.add_argument("--hover", required=True)
    ap.add_argument("--t-from-s", type=float, default=8.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vehicle", default=None, help="also fly this vehicle class with the spec (e.g. racing5)")
    ap.add_argument("--vehicle-duration-s", type=float, default=12.0)
    ap.add_argument("--plot", default=None, help="PNG of the PSDs of bands 0, 4, 7 (with --vehicle)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = run(spec_path=a.spec, hover_path=a.hover, t_from_s=a.t_from_s, seed=a.seed, vehicle=a.vehicle,
              vehicle_duration_s=a.vehicle_duration_s, plot=a.plot)
    if a.json:
        print(json.dumps(out, indent=1))
        return
    d = 180 / math.pi
    if a.vehicle:
        v = a.vehicle
        print(f"| band (motor cmd) | axis | in-band: F450 defaults | F450 + shaped (open loop) | {v} + spec physics | "
              f"{v} + physics + shaped | rms >40 Hz, deg/s: F450 / {v} physics / {v} physics+shaped / real |")
        print("|---|---|---|---|---|---|---|")
    else:
        print("| band (motor cmd) | axis | in-band before | in-band after | rms >40 Hz sim before / after / real, deg/s |")
        print("|---|---|---|---|---|")
    for r in out["rows"]:
        for ax in "xyz":
            b, af = r["before"][ax], r["after"][ax]
            if a.vehicle:
                ph, ps = r["physics"][ax], r["physics_shaped"][ax]
                print(f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | "
                      f"{af['in_band_fraction']:.2f} | {ph['in_band_fraction']:.2f} | {ps['in_band_fraction']:.2f} | "
                      f"{b['rms_sim_rad_s'] * d:.2f} / {ph['rms_sim_rad_s'] * d:.2f} / {ps['rms_sim_rad_s'] * d:.2f} / "
                      f"{b['rms_real_rad_s'] * d:.2f} |")
            else:
                print(f"| {r['throttle'][0]:.2f}-{r['throttle'][1]:.2f} | {ax} | {b['in_band_fraction']:.2f} | {af['in_band_fraction']:.2f} | "
                      f"{b['rms_sim_rad_s'] * d:.2f} / {af['rms_sim_rad_s'] * d:.2f} / {b['rms_real_rad_s'] * d:.2f} |")


if __name__ == "__main__":
    main()
