"""Monograph chapter 3 range channels against the Singer channel: reproduction targets K5, K6, K7
of the kalman-filters digest §13, with common random numbers over N Monte-Carlo runs.

* K5  kinematic-parameter channel (§3.4) beats Singer: σ_D, σ_V, σ_a (real RMSE (2.15), N − 1).
* K6  kinematic + dynamic channel (§3.5) beats kinematic only: σ_D; (3.62) printed and corrected.
* K7  CV filter (§2.3, Q = diag(D_Dx, 0)) on a non-manoeuvring target: real σ ≈ potential √P⁺,
      gains fall to steady values; on a non-linear LOS trajectory real ≫ potential.

Trajectories: the §3.4.6 stressing segment (300 m/s, R = 5 000 m turn, τ = 0.1 s, 500 m; radar at
the origin, 10 s straight before the 90° left turn and 5 s after, ranges 4.0–8.1 km) and the
big box (:func:`tertiary.simulate.traffic.big_box`, as reproduce_filter_orderings.py uses via
load_scenario("big-box"); radar RLS1 of that scenario, τ = 1 s). Radar plots: range, azimuth,
elevation + Gaussian noise with RLS1's σ (50 m, 0.1°, 0.1°) at every grid time; the datalink
carries Mode S EHS parameters (:mod:`tertiary.simulate.ehs`) at the same times. Every filter of a
trajectory sees the same noise (common random numbers).

    python benchmarks/reproduce_kinematic_channels.py [--runs 100]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _util import record
from tertiary.filters import kinematic_los as los
from tertiary.filters.kinematic import (KinematicDynamicRangeChannel, KinematicRangeChannel, channel_inputs, dynamic_aux, kinematic_aux)
from tertiary.filters.singer import (predict_elementwise, singer_coefficients, update_elementwise)
from tertiary.simulate import load_scenario
from tertiary.simulate.ehs import ehs_parameters
from tertiary.simulate.traffic import BIG_BOX_TURN_RATE, big_box
from tertiary.simulate.trajectory import SEG_STRAIGHT, SEG_TURN, Trajectories, integrate_commands

SEED = 20211007
SEG_V, SEG_R, SEG_DT, SEG_ALT = 300.0, 5000.0, 0.1, 500.0


def segment() -> tuple[Trajectories, np.ndarray]:
    """§3.4.6 segment: 10 s north, 90° left turn of radius 5 000 m (262 steps of 0.1 s, 90.07°), 5 s west."""
    rate = -np.degrees(SEG_V / SEG_R)
    turn = np.concatenate([np.zeros(100), np.full(262, rate), np.zeros(50)])[None, :]
    pos, vel = integrate_commands(np.array([[7000.0, -4000.0, SEG_ALT]]), np.array([0.0]),
                                  np.full_like(turn, SEG_V), turn, np.zeros_like(turn), SEG_DT)
    w = np.radians(np.append(turn[0], turn[0, -1]))
    seg = np.where(w != 0, SEG_TURN, SEG_STRAIGHT).astype(np.int8)[None, :]
    traj = Trajectories(dt=SEG_DT, pos=pos, vel=vel, active=np.ones(pos.shape[:2], bool), segment=seg,
                        truth_id=np.array([0], np.int64))
    return traj, w


def bigbox() -> tuple[Trajectories, np.ndarray]:
    traj = big_box(1.0)
    w = np.where(traj.segment[0] == SEG_TURN, np.radians(BIG_BOX_TURN_RATE), 0.0)
    return traj, w


def truth(traj: Trajectories, w: np.ndarray) -> dict[str, np.ndarray]:
    """True D, Ḋ, D̈ (fixed radar at the origin) with the commanded acceleration a = ψ̇ (v_n, −v_e, 0)."""
    p, v = traj.pos[0], traj.vel[0]
    acc = np.stack([w * v[:, 1], -w * v[:, 0], np.zeros_like(w)], axis=1)
    r, vn, an = los.enu_to_normal(p), los.enu_to_normal(v), los.enu_to_normal(acc)
    d = np.linalg.norm(r, axis=1)
    return {"D": d, "V": los.los_rates(r, vn)[0], "a": los.range_acceleration_truth(r, vn, an),
            "turn": traj.segment[0] == SEG_TURN, "t": traj.times}


def measurements(traj: Trajectories, runs: int, sig_r: float, sig_ang_deg: float, rng: np.random.Generator
                 ) -> dict[str, np.ndarray]:
    """(T, N) channel inputs: noisy radar plot + EHS parameters at every grid time."""
    t_n = traj.n_times
    e, n, u = traj.pos[0].T
    rng_m = np.sqrt(e * e + n * n + u * u)
    az = np.degrees(np.arctan2(e, n))
    el = np.degrees(np.arcsin(u / rng_m))
    noise = rng.standard_normal((3, t_n, runs))
    t = np.repeat(traj.times[:, None], runs, axis=1)
    ehs, ok = ehs_parameters(traj, np.zeros(t.shape, np.int64), t, rng)
    assert ok.all()
    return channel_inputs(rng_m[:, None] + sig_r * noise[0], az[:, None] + sig_ang_deg * noise[1],
                          el[:, None] + sig_ang_deg * noise[2], ehs["ground_speed_mps"], ehs["true_track_deg"],
                          ehs["vertical_rate_mps"], ehs["roll_deg"])


def run_singer(z: np.ndarray, tau: float, sig_r: float, alpha: float, sigma_m: float, v0: float = 300.0
               ) -> dict[str, np.ndarray]:
    """The per-radar Singer range channel (printed (2.49)–(2.63), tertiary.sensors.local_tracks' kernels)."""
    t_n, b = z.shape
    x = np.zeros((3, b))
    x[0] = z[0]
    p = np.zeros((6, b))
    p[0], p[3], p[5] = sig_r**2, v0**2, sigma_m**2
    coeffs = singer_coefficients(np.full(b, tau), alpha, sigma_m, "printed")
    out = {k: np.empty((t_n, b)) for k in ("D", "V", "a", "P00")}
    for k in range(t_n):
        if k:
            predict_elementwise(x, p, np.full(b, tau), coeffs)
            update_elementwise(x, p, z[k] - x[0], np.full(b, sig_r**2))
        out["D"][k], out["V"][k], out["a"][k], out["P00"][k] = x[0], x[1], x[2], p[0]
    return out


def real_sigma(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(2.15): per-step √(Σ_j (x − x_j⁺)²/(N − 1))."""
    return np.sqrt(np.sum((est - true[:, None]) ** 2, axis=1) / (est.shape[1] - 1))


def summarise(out: dict[str, np.ndarray], tr: dict[str, np.ndarray], warm: np.ndarray) -> dict[str, dict[str, float]]:
    res = {}
    for win, m in (("all", warm), ("turn", warm & tr["turn"]), ("straight", warm & ~tr["turn"])):
        res[win] = {f"sigma_{c}": float(np.mean(real_sigma(out[c], tr[c])[m])) for c in ("D", "V", "a")}
    return res


def compare(name: str, traj: Trajectories, w: np.ndarray, runs: int, warm_s: float) -> dict:
    cfg = load_scenario("big-box").radars[0]
    sig_r, sig_a = cfg.sigma_range_m, cfg.sigma_azimuth_deg
    tr = truth(traj, w)
    z = measurements(traj, runs, sig_r, sig_a, np.random.default_rng(SEED))
    tau = traj.dt
    warm = tr["t"] >= warm_s
    speed = float(np.median(np.linalg.norm(traj.vel[0], axis=1)))
    sigma_match = float(np.sqrt(np.mean(tr["a"][warm] ** 2)))
    kw = {"sigma_range_m": sig_r}
    filters = {
        "singer(sigma_m=2)": lambda: run_singer(z["range_m"], tau, sig_r, 1 / 30, 2.0),
        f"singer(sigma_m={sigma_match:.2f})": lambda: run_singer(z["range_m"], tau, sig_r, 1 / 30, sigma_match),
        "kinematic": lambda: KinematicRangeChannel(aux=kinematic_aux(np.radians(sig_a), speed), **kw).run(z, tau),
        "kinematic(printed 3.11)": lambda: KinematicRangeChannel(
            variant="printed", aux=kinematic_aux(np.radians(sig_a), speed), **kw).run(z, tau),
        "kinematic_dynamic(printed)": lambda: KinematicDynamicRangeChannel(
            variant="printed", aux=dynamic_aux(np.radians(sig_a), speed), **kw).run(z, tau),
        "kinematic_dynamic(corrected)": lambda: KinematicDynamicRangeChannel(
            variant="corrected", aux=dynamic_aux(np.radians(sig_a), speed), **kw).run(z, tau),
    }
    res, secs = {}, {}
    for fname, fn in filters.items():
        t0 = time.perf_counter()
        res[fname] = summarise(fn(), tr, warm)
        secs[fname] = round(time.perf_counter() - t0, 3)
    singer_best = min((k for k in res if k.startswith("singer")), key=lambda k: res[k]["all"]["sigma_D"])
    verdict = {}
    for win in ("all", "turn"):
        sb, kin = res[singer_best][win], res["kinematic"][win]
        verdict[win] = {
            "K5 kinematic < best singer (D, V, a)": [kin[c] < sb[c] for c in ("sigma_D", "sigma_V", "sigma_a")],
            "K5 vs singer(sigma_m=2) (D, V, a)": [kin[c] < res["singer(sigma_m=2)"][win][c]
                                                  for c in ("sigma_D", "sigma_V", "sigma_a")],
            "K5 printed (3.11) < best singer (D, V, a)": [res["kinematic(printed 3.11)"][win][c] < sb[c]
                                                          for c in ("sigma_D", "sigma_V", "sigma_a")],
            "K6 printed: kd < kinematic (sigma_D)": res["kinematic_dynamic(printed)"][win]["sigma_D"] < kin["sigma_D"],
            "K6 corrected: kd < kinematic (sigma_D)": res["kinematic_dynamic(corrected)"][win]["sigma_D"] < kin["sigma_D"],
        }
    return {"trajectory": name, "tau_s": tau, "steps": traj.n_times, "runs": runs, "warm_up_s": warm_s,
            "sigma_range_m": sig_r, "sigma_angle_deg": sig_a, "peak_abs_Ddd_mps2": float(np.abs(tr["a"]).max()),
            "singer_matched_sigma_m": sigma_match, "best_singer": singer_best, "results": res,
            "verdicts": verdict, "seconds": secs}


# ----------------------------------------------------------------------------- K7

def cv_range(z: np.ndarray, tau: float, r: float, d_dx: float) -> dict[str, np.ndarray]:
    """§2.3 scalar CV filter (2.24)–(2.31), Q = diag(D_Dx, 0), two-point initiation (digest §3):
    D⁺(1) = z(1), V⁺(1) = (z(1) − z(0))/τ, P⁺(1) = [[R, R/τ], [R/τ, 2R/τ²]] (estimates from k = 1)."""
    t_n, b = z.shape
    d, v = z[1].copy(), (z[1] - z[0]) / tau
    p11, p12, p22 = r, r / tau, 2 * r / tau**2
    out = {k: np.full((t_n, b), np.nan) for k in ("D", "V")} | {k: np.full(t_n, np.nan) for k in ("P11", "P22", "K1", "K2")}
    for k in range(1, t_n):
        if k > 1:
            m11, m12, m22 = p11 + 2 * tau * p12 + tau * tau * p22 + d_dx, p12 + tau * p22, p22   # (2.29)
            s = m11 + r
            k1, k2 = m11 / s, m12 / s                                                            # (2.30)
            d, v = d + v * tau, v                                                                # (2.26)–(2.27)
            nu = z[k] - d                                                                        # (2.28)
            d, v = d + k1 * nu, v + k2 * nu                                                      # (2.24)–(2.25)
            p11, p12, p22 = r * k1, r * k2, m22 - k2 * m12                                       # (2.31)
            out["K1"][k], out["K2"][k] = k1, k2
        out["D"][k], out["V"][k] = d, v
        out["P11"][k], out["P22"][k] = p11, p22
    return out


K7_STEPS = (2, 3, 5, 20, 100, 200, 299)


def k7(runs: int) -> dict:
    """CV on a radially outbound constant-speed target (D̈ = 0) vs a tangential pass (D̈ ≠ 0), with
    the matched D_Dx = 0 and with D_Dx = 1 m² (a disturbance the target does not have)."""
    sig_r, tau, t_n = 50.0, 1.0, 300
    t = np.arange(t_n) * tau
    rng = np.random.default_rng(SEED + 7)
    noise = sig_r * rng.standard_normal((t_n, runs))
    cases = {"radial (a = 0)": (10_000.0 + 100.0 * t, np.full(t_n, 100.0)),
             "tangential pass (a != 0)": (np.hypot(5_000.0, 100.0 * (t - 150.0)),
                                          100.0 * 100.0 * (t - 150.0) / np.hypot(5_000.0, 100.0 * (t - 150.0)))}
    res = {}
    for d_dx in (0.0, 1.0):
        for name, (d_true, v_true) in cases.items():
            o = cv_range(d_true[:, None] + noise, tau, sig_r**2, d_dx=d_dx)
            late = t >= 2
            ratio_d = real_sigma(o["D"], d_true) / np.sqrt(o["P11"])
            ratio_v = real_sigma(o["V"], v_true) / np.sqrt(o["P22"])
            res[f"{name}, D_Dx={d_dx:g}"] = {
                "ratio_real_to_potential_D_mean": float(np.mean(ratio_d[late])),
                "ratio_real_to_potential_V_mean": float(np.mean(ratio_v[late])),
                "ratio_D_max": float(np.max(ratio_d[late])), "ratio_V_max": float(np.max(ratio_v[late])),
                "k": list(K7_STEPS), "K1": [float(o["K1"][k]) for k in K7_STEPS],
                "K2": [float(o["K2"][k]) for k in K7_STEPS]}
    verdict = {}
    for d_dx in (0.0, 1.0):
        rad, tan = res[f"radial (a = 0), D_Dx={d_dx:g}"], res[f"tangential pass (a != 0), D_Dx={d_dx:g}"]
        # N runs: the sampling error of a σ estimate is ≈ 1/√(2N) (7 % at N = 100): "close" = within 15 %
        verdict[f"D_Dx={d_dx:g}"] = {
            "real close to potential on a = 0 (D, V means within 15 %)":
                abs(rad["ratio_real_to_potential_D_mean"] - 1) < 0.15 and abs(rad["ratio_real_to_potential_V_mean"] - 1) < 0.15,
            "gains fall monotonically": bool(np.all(np.diff(rad["K1"]) <= 0) and np.all(np.diff(rad["K2"]) <= 0)),
            "K1 steady (K1(299)/K1(200) > 0.95)": rad["K1"][-1] / rad["K1"][-2] > 0.95,
            "real >> potential on the non-linear LOS pass (D ratio max > 2)": tan["ratio_D_max"] > 2.0,
        }
    res["verdict"] = verdict
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    args = ap.parse_args()
    out = {"runs": args.runs, "segment_3_4_6": compare("segment 3.4.6", *segment(), args.runs, warm_s=5.0),
           "big_box": compare("big box", *bigbox(), args.runs, warm_s=20.0), "K7": k7(args.runs)}
    for key in ("segment_3_4_6", "big_box"):
        r = out[key]
        print(f"\n{r['trajectory']}: tau {r['tau_s']} s, N = {r['runs']}, peak |D''| {r['peak_abs_Ddd_mps2']:.2f} m/s2")
        for win in ("all", "turn"):
            print(f"  window {win}:")
            for f, v in r["results"].items():
                m = v[win]
                print(f"    {f:34s} sD {m['sigma_D']:8.3f}  sV {m['sigma_V']:8.3f}  sa {m['sigma_a']:8.3f}")
            print("   ", r["verdicts"][win])
    print("\nK7:", out["K7"]["verdict"])
    for name, v in out["K7"].items():
        if name != "verdict":
            print(" ", name, {k: (round(x, 3) if isinstance(x, float) else x) for k, x in v.items()})
    print(f"recorded in {record('reproduce_kinematic_channels', out)}")


if __name__ == "__main__":
    main()
