"""Out-of-bank mismatch detection against its physical bound: is a mesh the bank does not
hold detected, and could any test have detected it?

For each out-of-bank truth (a mesh not in the bank, random attitude, material and
roughness, seeded) this bench

1. inverts its *noise-free* expected counts ``mu_true`` (SNR 1000 scale) with
   ``inversion.invert`` (the same classify / refine / modes / index path as real data; the
   Poisson deviance accepts non-integer counts): the deviance at that fit is the
   noncentrality ``lambda = D(mu_true, mu_0)`` of the closest in-bank expectation found;
2. inverts Poisson draws at every SNR (30, 100, 1000) and records ``model_mismatch``
   (goodness of fit, p < 1e-3);
3. takes ``lambda`` at each SNR as the smallest deviance of ``mu_true`` from any in-bank
   expectation at hand: the noise-free fit's and every noisy fit's, rescaled by the gain
   (free in the bank's models, so ``c mu`` is an in-bank expectation too; any in-bank
   expectation gives a valid bound, the closest the tightest);
4. reports the Neyman-Pearson bound ``Phi(sqrt(lambda) - z_alpha)`` on the power of any
   level-1e-3 test (``inversion.detection_power_bound``), that likelihood-ratio test's
   power simulated with Poisson draws (checks the normal limit), and the power of the
   goodness-of-fit test at that ``lambda`` (``inversion.detection_power`` with the noisy
   fit's null law).

Posterior sampling is off: the goodness of fit is computed at the final fit, before
sampling, so the verdict is the one ``inversion.invert`` gives with sampling on.

Meshes (none in the bank of 1U, 3U, 12-sided cylinder): the three of
``bench_inversion.py`` (box with an off-axis panel, 3U 20 % wider, 3U tapered) and a 1U with
one deployed solar panel (cover glass), a 6U, a 12U, a 3U with an antenna boom, and the
bank's cylinder with end caps of another material.

Run: ``python bench/bench_inversion_oob.py [--n-per-mesh 4] [--resume]`` (x64; writes
``bench/results/inversion_oob.md`` and ``.json``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_inversion as bi  # noqa: E402  (x64 and the compilation cache are set there)
import numpy as np  # noqa: E402
from scipy import optimize  # noqa: E402

import inversion  # noqa: E402
import ppr  # noqa: E402

OUT = bi.OUT
ALPHA = 1e-3
SNR_REF = 1000.0
N_LR_DRAWS = 20000


def wing_1u() -> ppr.Mesh:
    """A 1U cube with one deployed solar panel (20 x 10 cm, 2 mm thick) on its +y face in
    the x = 0 plane; the panel's +x face is cover glass (part ``solar_panel``)."""
    body = ppr.shapes.cubesat(1)
    pm = ppr.shapes.box((0.002, 0.2, 0.1))
    v = np.asarray(pm.vertices) + np.array([0.0, 0.05 + 0.1, 0.0])
    tri = v[np.asarray(pm.faces)]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = nrm[:, 0] > 0.5 * np.linalg.norm(nrm, axis=1)
    panel = ppr.Mesh(v, pm.faces, np.where(front, 1, 0).astype(np.int32), ("body", "solar_panel"))
    return ppr.geometry.concatenate([body, panel])


def box_6u() -> ppr.Mesh:
    """A 6U CubeSat: 0.2 x 0.1 x 0.34 m."""
    return ppr.shapes.cubesat(6)


def box_12u() -> ppr.Mesh:
    """A 12U CubeSat: 0.2 x 0.2 x 0.34 m."""
    return ppr.shapes.box((0.2, 0.2, 0.34))


def boom_3u() -> ppr.Mesh:
    """A 3U CubeSat with a 25 cm antenna boom (1 x 1 cm) along +x from its +x face, 12 cm
    up from the centre."""
    body = ppr.shapes.cubesat(3)
    boom = ppr.shapes.box((0.25, 0.01, 0.01))
    v = np.asarray(boom.vertices) + np.array([0.05 + 0.125, 0.0, 0.12])
    return ppr.geometry.concatenate([body, ppr.Mesh(v, boom.faces, None, ("body",))])


def capped_cylinder() -> ppr.Mesh:
    """The bank's cylinder (r 6 cm, 25 cm, 12 sections) with its end caps a separate part
    (``caps``): the geometry is in the bank, the two-material surface is not."""
    cyl = ppr.shapes.cylinder(0.06, 0.25, sections=12)
    tri = np.asarray(cyl.vertices, np.float64)[np.asarray(cyl.faces)]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cap = np.abs(nrm[:, 2]) > 0.9 * np.linalg.norm(nrm, axis=1)
    return ppr.Mesh(cyl.vertices, cyl.faces, cap.astype(np.int32), ("body", "caps"))


OOB = {
    **bi.OUT_OF_BANK,
    "1u+wing": wing_1u,
    "6u": box_6u,
    "12u": box_12u,
    "3u+boom": boom_3u,
    "cyl+caps": capped_cylinder,
}


def random_truths(n, rng, names, meshes):
    """``n`` truths cycling through ``names``: uniform attitude, log-uniform roughness (one
    per truth), range offset within +-3 bins, a random library material per part (the solar
    panel is fused silica, the cylinder's caps differ from its body)."""
    out = []
    for j in range(n):
        name = names[j % len(names)]
        q = rng.normal(size=4)
        mats = []
        for part in meshes[name].parts:
            if part == "solar_panel":
                mats.append("fused_silica")
                continue
            choices = [m for m in bi.MATERIALS if m not in mats]
            mats.append(choices[int(rng.integers(len(choices)))])
        out.append(
            dict(
                shape=name,
                q=q / np.linalg.norm(q),
                materials=mats,
                m=float(math.exp(rng.uniform(*np.log(bi.M_RANGE)))),
                offset=float(rng.uniform(-3.0, 3.0) * bi.BIN_WIDTH),
            )
        )
    return out


def expected_counts(model, t, snr):
    """The truth's expected counts with SNR^2 counts in all (as ``bench_inversion.observe``),
    per-part materials."""
    n = [complex(np.asarray(ppr.load_material(m).n)) for m in t["materials"]]
    k = len(model.scene.mesh.parts)
    p = inversion.PhysicalParams(t["q"], [t["m"]] * k, n, range_offset=t["offset"])
    x = np.maximum(np.asarray(model.expected(p, model.prepare(p)), np.float64), 0.0)
    return x * (snr**2 / x.sum())


def lr_power_simulated(mu1, mu0, b, rng, n=N_LR_DRAWS, alpha=ALPHA):
    """Power of the Neyman-Pearson test of ``mu0`` against ``mu1`` (data: Poisson draws of
    ``mu1``, as the observations; the model adds the background ``b``), its critical value
    the ``1 - alpha`` quantile of the statistic under ``mu0`` (both from ``n`` draws)."""
    lam1, lam0 = mu1.ravel() + b, mu0.ravel() + b
    w = np.log(lam1 / lam0)
    t0, t1 = [], []
    for lo in range(0, n, 2000):
        m = min(2000, n - lo)
        t0.append(rng.poisson(lam0, size=(m, w.size)) @ w)
        t1.append(rng.poisson(mu1.ravel(), size=(m, w.size)) @ w)
    crit = np.quantile(np.concatenate(t0), 1.0 - alpha)
    return float(np.mean(np.concatenate(t1) > crit))


def one_truth(j, t, oob_models, models, prep, cfg, snrs):
    """Noise-free inversion and one noisy inversion per SNR of truth ``j``; ``lambda``, the
    bounds and the detection per SNR."""
    noise = inversion.PoissonCounts(background=cfg.background)
    model = oob_models[t["shape"]]
    mu_ref = expected_counts(model, t, SNR_REF)
    t0 = time.perf_counter()
    inv0 = inversion.invert(mu_ref, models, config=cfg, bank=prep)
    nf = dict(
        fit_shape=inv0.shape,
        deviance=inv0.goodness_of_fit.deviance,
        converged=inv0.converged,
        wall_s=time.perf_counter() - t0,
    )
    # in-bank expectations at SNR_REF scale (gain free: c mu is in the bank too)
    cands = [("noise-free fit", inv0.expected)]
    noisy = {}
    for snr in snrs:
        mu = mu_ref * (snr / SNR_REF) ** 2
        data = np.random.default_rng(7000 + 10 * j + int(snr)).poisson(mu).astype(np.float64)
        t1 = time.perf_counter()
        inv = inversion.invert(data, models, config=cfg, bank=prep)
        noisy[snr] = (inv, time.perf_counter() - t1)
        cands.append((f"fit at SNR {snr:g}", inv.expected * (SNR_REF / snr) ** 2))
    recs = []
    rng = np.random.default_rng(90_000 + j)
    for snr in snrs:
        inv, wall = noisy[snr]
        c = (snr / SNR_REF) ** 2
        mu = mu_ref * c
        devs = [inversion.goodness_of_fit(mu, e * c, noise, n_params=0).deviance for _, e in cands]
        k = int(np.argmin(devs))
        lam = float(devs[k])
        gof = inv.goodness_of_fit
        bound = inversion.detection_power_bound(lam, ALPHA)
        lr = (
            lr_power_simulated(mu, cands[k][1] * c, cfg.background, rng)
            if 1e-3 < bound < 0.999
            else None
        )
        recs.append(
            dict(
                truth=j,
                shape=t["shape"],
                materials=t["materials"],
                m_true=t["m"],
                snr=snr,
                fit_shape=inv.shape,
                p_value=gof.p_value,
                p_components={c.name: c.p_value for c in gof.components},
                detected_deviance=bool(gof.components[0].p_value < gof.threshold),
                z=gof.z,
                detected=bool(gof.model_mismatch),
                null_mean=gof.expected,
                null_std=gof.std,
                lam=lam,
                lam_from=cands[k][0],
                lam_noise_free=float(devs[0]),
                bound=bound,
                lr_simulated=lr,
                test_power=inversion.detection_power(lam, gof, ALPHA),
                test_power_chi2=inversion.detection_power(lam, gof.dof, ALPHA),
                noise_free=nf,
                wall_s=wall,
                converged=inv.converged,
            )
        )
    return recs


# ------------------------------------------------------------------------ summary
def rate(rs):
    return bi.fmt_rate(sum(r["detected"] for r in rs), len(rs))


def rate_dev(rs):
    """Detection rate of the deviance over all values alone (before the marginal tests)."""
    return bi.fmt_rate(sum(r.get("detected_deviance", r["detected"]) for r in rs), len(rs))


def heldout_alarms() -> str:
    """In-bank false-alarm rate of the last held-out run (``inversion_heldout.json``)."""
    src = OUT / "inversion_heldout.json"
    try:
        recs = json.loads(src.read_text())["observations"]
        inb = [r for r in recs if r["kind"] == "in"]
        return bi.fmt_rate(sum(bool(r["mismatch"]) for r in inb), len(inb))
    except (OSError, KeyError, ValueError, TypeError):
        return "(no held-out run found)"


def summarize(records, meta) -> str:
    hi = [r for r in records if r["snr"] >= 100]
    det = [r for r in hi if r["bound"] >= 0.95]
    und = [r for r in hi if r["bound"] < 0.95]
    k_det = sum(r["detected"] for r in det)
    ok_target = bool(det) and k_det / len(det) >= 0.95
    lines = [
        "# Out-of-bank mismatch detection against its physical bound" + meta.get("title", ""),
        "",
        f"Command: `{meta['command']}` (x64, BRDF `ppr.mueller_brdf`, 16 PSG/PSA channels, "
        f"64 bins of 1 cm). {meta['n_truths']} out-of-bank truths ({meta['per_mesh']} per "
        f"mesh, seed {meta['seed']}), each observed at SNR {meta['snrs']} (Poisson counts, "
        "SNR = sqrt(total counts)) and inverted with `inversion.invert` against the bank "
        f"({meta['n_templates']} templates: {list(bi.SHAPES)} x Hopf nside {meta['grid']} x "
        f"{len(bi.MATERIALS)} materials x {len(bi.FINISHES)} finishes; posterior sampling off, "
        "the goodness of fit precedes it); truths: uniform attitude, a library material per "
        f"part, m log-uniform in {list(bi.M_RANGE)}, range offset within +-3 bins. Warm-up "
        f"(compilation) {meta['compile_s']:.0f} s; total {meta['total_s']:.0f} s; load average "
        f"{meta['load']}.",
        "",
        "`lambda`: deviance of the truth's noise-free counts from the closest in-bank "
        "expectation found (the noise-free inversion's fit or any noisy fit, rescaled by the "
        "gain). `bound`: `Phi(sqrt(lambda) - z_alpha)`, the most any level-1e-3 test can "
        "detect (`inversion.detection_power_bound`); `LR sim`: that likelihood-ratio test's "
        f"power from {N_LR_DRAWS} Poisson draws per hypothesis (where the bound is between "
        "1e-3 and 0.999); `GoF power`: the power at that lambda of the deviance over all "
        "values (`inversion.detection_power` with the observation's null law); `detected`: "
        "`model_mismatch`, the Bonferroni combination of that deviance with the range-profile "
        'and channel-total tests (`inversion.goodness_of_fit`, "Marginal tests"); `p`: '
        "the combined p-value and the three components' (all / profile / totals).",
        "",
        "## Verdict",
        "",
        "| measure (SNR >= 100) | value |",
        "|---|---|",
        f"| detected, all out-of-bank observations | {rate(hi)} |",
        f"| detected, physically detectable (bound >= 0.95) | {rate(det)} "
        f"(target >= 0.95: **{'met' if ok_target else 'not met'}**) |",
        f"| detected, bound < 0.95 | {rate(und)} |",
        "| detected, goodness-of-fit power >= 0.95 (what this test can see) | "
        f"{rate([r for r in hi if r['test_power'] >= 0.95])} |",
        "| detected, bound >= 0.95 but goodness-of-fit power < 0.95 | "
        f"{rate([r for r in det if r['test_power'] < 0.95])} |",
        f"| sum of bounds, bound < 0.95 (most any test could detect) | "
        f"{sum(r['bound'] for r in und):.2f} of {len(und)} |",
        f"| sum of deviance-test powers, all (its expected detections) | "
        f"{sum(r['test_power'] for r in hi):.1f} (the deviance alone detected "
        f"{sum(r.get('detected_deviance', r['detected']) for r in hi)}) |",
        f"| detected by the deviance alone, physically detectable | {rate_dev(det)} |",
        "| in-bank false alarms (last held-out run, `inversion_heldout.md`) | "
        f"{heldout_alarms()} |",
        "",
        "## Per SNR",
        "",
        "| SNR | n | detected | bound >= 0.95 | detected among those | median lambda |",
        "|---|---|---|---|---|---|",
    ]
    for snr in meta["snrs"]:
        rs = [r for r in records if r["snr"] == snr]
        d = [r for r in rs if r["bound"] >= 0.95]
        lines.append(
            f"| {snr:g} | {len(rs)} | {rate(rs)} | {len(d)} | {rate(d)} | "
            f"{np.median([r['lam'] for r in rs]):.3g} |"
        )
    nm = np.percentile([r["null_mean"] for r in records], [0, 50, 100])

    def lam95(dof):
        """Noncentrality at which the bound (dof None) or the chi-square test reaches 0.95."""

        def f(lam):
            if dof is None:
                return inversion.detection_power_bound(lam, ALPHA) - 0.95
            return inversion.detection_power(lam, dof, ALPHA) - 0.95

        return optimize.brentq(f, 1e-6, 1e5)

    lines += [
        "",
        "## By noncentrality (all SNRs)",
        "",
        f"lambda = {lam95(None):.1f} is where the bound reaches 0.95. The goodness-of-fit "
        "test spreads its power over every direction of misfit: its null deviance here has "
        f"mean {nm[0]:.0f}-{nm[2]:.0f} (median {nm[1]:.0f}; 1024 values, most without "
        "signal), so like a chi-square with that many degrees of freedom it needs lambda = "
        f"{lam95(nm[0]):.0f}-{lam95(nm[2]):.0f} (median {lam95(nm[1]):.0f}) for a power of "
        "0.95.",
        "",
        "| lambda | n | detected | mean bound | mean LR sim | mean GoF power |",
        "|---|---|---|---|---|---|",
    ]
    edges = [0.0, 5.0, round(lam95(None), 1), 100.0, 230.0, math.inf]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        rs = [r for r in records if a <= r["lam"] < b]
        if not rs:
            continue
        lr = [r["lr_simulated"] for r in rs if r["lr_simulated"] is not None]
        lines.append(
            f"| [{a:g}, {b:g}) | {len(rs)} | {rate(rs)} | "
            f"{np.mean([r['bound'] for r in rs]):.3f} | "
            f"{np.mean(lr) if lr else float('nan'):.3f} ({len(lr)}) | "
            f"{np.mean([r['test_power'] for r in rs]):.3f} |"
        )
    lines += [
        "",
        "## Per mesh (SNR >= 100)",
        "",
        "| mesh | n | detected | bound >= 0.95 | detected among those | lambda range |",
        "|---|---|---|---|---|---|",
    ]
    for name in OOB:
        rs = [r for r in hi if r["shape"] == name]
        if not rs:
            continue
        d = [r for r in rs if r["bound"] >= 0.95]
        lam = [r["lam"] for r in rs]
        lines.append(
            f"| {name} | {len(rs)} | {rate(rs)} | {len(d)} | {rate(d)} | "
            f"{min(lam):.3g} - {max(lam):.3g} |"
        )
    lines += [
        "",
        "## Every observation",
        "",
        "| truth | mesh | materials | m | SNR | fit shape | p (all / profile / totals) | "
        "detected | lambda (from) | bound | LR sim | GoF power |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        lr = "-" if r["lr_simulated"] is None else f"{r['lr_simulated']:.3f}"
        pc = r.get("p_components") or {}
        parts = " / ".join(f"{v:.2g}" for v in pc.values())
        lines.append(
            f"| {r['truth']} | {r['shape']} | {'/'.join(r['materials'])} | {r['m_true']:.0f} | "
            f"{r['snr']:g} | {r['fit_shape']} | {r['p_value']:.2g}"
            f"{f' ({parts})' if parts else ''} | "
            f"{'yes' if r['detected'] else 'no'} | {r['lam']:.3g} ({r['lam_from']}) | "
            f"{r['bound']:.3f} | {lr} | {r['test_power']:.3f} |"
        )
    lr_rows = [r for r in records if r["lr_simulated"] is not None]
    if lr_rows:
        diff = [r["lr_simulated"] - r["bound"] for r in lr_rows]
        lines += [
            "",
            f"Normal limit of the likelihood-ratio test: simulated power minus "
            f"`Phi(sqrt(lambda) - z_alpha)` over the {len(lr_rows)} observations with an "
            f"informative bound: median {np.median(diff):+.3f}, range {min(diff):+.3f} to "
            f"{max(diff):+.3f}.",
        ]
    t = [r["wall_s"] for r in records]
    lines += [
        "",
        f"Time per noisy inversion (no sampling): median {np.median(t):.1f} s wall.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-per-mesh", type=int, default=4, help="truths per out-of-bank mesh")
    ap.add_argument("--meshes", nargs="+", default=list(OOB), choices=list(OOB))
    ap.add_argument("--snrs", type=float, nargs="+", default=[30.0, 100.0, 1000.0])
    ap.add_argument("--grid", type=int, default=2, help="Hopf nside of the bank")
    ap.add_argument("--seed", type=int, default=2027)
    ap.add_argument("--tag", default="")
    ap.add_argument(
        "--heldout-truths",
        action="store_true",
        help="the 4 out-of-bank truths of inversion_heldout.md instead of new ones",
    )
    ap.add_argument(
        "--resume",
        action="store_true",
        help="continue a stopped run, or extend a finished one (same seed, more truths)",
    )
    ap.add_argument("--summarize", metavar="JSON", help="only rewrite the .md of a .json")
    args = ap.parse_args(argv)
    if args.summarize:
        src = Path(args.summarize)
        res = json.loads(src.read_text())
        src.with_suffix(".md").write_text(summarize(res["observations"], res["meta"]))
        return
    t_all = time.perf_counter()
    models = {k: bi.make_model(f()) for k, f in bi.SHAPES.items()}
    oob_meshes = {k: OOB[k]() for k in (list(OOB) if args.heldout_truths else args.meshes)}
    oob_models = {k: bi.make_model(m) for k, m in oob_meshes.items()}
    mats = {m: complex(np.asarray(ppr.load_material(m).n)) for m in bi.MATERIALS}
    bank = inversion.screening_bank(models, mats, bi.FINISHES, grid={"size": args.grid})
    prep = inversion.prepare(bank)
    cfg = inversion.InvertConfig(
        materials=bi.MATERIALS, finishes=bi.FINISHES, top_k=4, mcmc=None, mismatch_p=ALPHA
    )
    rng = np.random.default_rng(args.seed)
    n = args.n_per_mesh * len(args.meshes)
    truths = random_truths(n, rng, args.meshes, oob_meshes)
    if args.heldout_truths:  # the out-of-bank truths of `bench_inversion.py --n-in 8 --n-out 4`
        rng = np.random.default_rng(2026)
        bi.random_truths(8, rng, list(bi.SHAPES))  # its in-bank truths come first
        truths = [
            dict(t, materials=[t["material"]])
            for t in bi.random_truths(4, rng, list(bi.OUT_OF_BANK))
        ]
        n = len(truths)
    t0 = time.perf_counter()  # warm-up: one in-bank observation compiles every program
    warm = bi.random_truths(1, np.random.default_rng(args.seed + 99), list(bi.SHAPES))[0]
    _, data = bi.observe(models[warm["shape"]], warm, 100.0, seed=99)
    inversion.invert(data, models, config=cfg, bank=prep)
    t_compile = time.perf_counter() - t0
    print(f"bank {len(bank)} templates; warm-up {t_compile:.1f} s", flush=True)
    partial = OUT / f".inversion_oob{args.tag}.partial.json"
    final = OUT / f"inversion_oob{args.tag}.json"
    records = []
    if args.resume and partial.exists():
        records = json.loads(partial.read_text())
    elif args.resume and final.exists():  # a finished run, extended (e.g. more truths per mesh)
        records = json.loads(final.read_text())["observations"]
    done = {r["truth"] for r in records}
    for j, t in enumerate(truths):
        if j in done:
            continue
        recs = one_truth(j, t, oob_models, models, prep, cfg, args.snrs)
        records += recs
        partial.write_text(json.dumps(records, default=str))
        for r in recs:
            print(
                f"[{j + 1}/{n}] {r['shape']}/{'/'.join(r['materials'])} m={r['m_true']:.0f} "
                f"snr={r['snr']:g} -> {r['fit_shape']} p={r['p_value']:.2g} "
                f"detected={r['detected']} lambda={r['lam']:.3g} bound={r['bound']:.3f} "
                f"lr={r['lr_simulated']} gof_power={r['test_power']:.3f} ({r['wall_s']:.1f} s)",
                flush=True,
            )
    meta = dict(
        title=": the 4 out-of-bank truths of `inversion_heldout.md`" if args.heldout_truths else "",
        command="python bench/bench_inversion_oob.py "
        + " ".join(sys.argv[1:] if argv is None else argv),
        n_truths=len({r["truth"] for r in records}),
        per_mesh="1-2" if args.heldout_truths else args.n_per_mesh,
        seed=2026 if args.heldout_truths else args.seed,
        snrs=args.snrs,
        grid=args.grid,
        n_templates=len(bank),
        compile_s=t_compile,
        total_s=time.perf_counter() - t_all,
        load=open("/proc/loadavg").read().split()[:3],
    )
    records.sort(key=lambda r: (r["truth"], r["snr"]))
    final.write_text(json.dumps(dict(meta=meta, observations=records), indent=1, default=str))
    (OUT / f"inversion_oob{args.tag}.md").write_text(summarize(records, meta))
    partial.unlink(missing_ok=True)
    print(summarize(records, meta))


if __name__ == "__main__":
    main()
