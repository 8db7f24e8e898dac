"""Two-frame captures: how registration's acceptance rules treat two rendered views of an object far apart, and
what the edges they refuse as weak geometry are worth (gscan.registration.pairwise, rule "weak geometry").

Each shared mesh rests on a table (--table) and is rendered at 640x480 (noisy depth) from cameras at 40 deg
elevation, at azimuth s and s + each gap (20 / 60 / 120 deg), for each start azimuth s of --starts
(bench/match.py's views); each pair is registered as a scan registers two frames, at the defaults
(`register_frames`: whole-frame keypoints, the pose refined on the depth and checked against the depth and the
texture; --masks: the object's pixels only). Right: within 5 deg and 2 cm of the ground truth.

Per gap: pairs registered at a right pose (%), registered at a wrong pose (count; must be 0), the pairs refused
because a turn of the object (half or, on object pixels, quarter) fits the two views as well (the rule for an
edge that alone places a frame, `gscan.registration.turns.lone_edge_turn`), split by their pose's actual error
(without that rule the wrong ones would have been registered), and the pairs refused as weak geometry split by
their pose's actual error: right (what a looser rule could gain) and wrong (what it would let through), both also
among those that pass every other rule (registered again without the bound: the depth and colour checks), with
the rotation sigma the refused edges claim against their actual rotation error (median ratio): a sigma that
understates the error cannot be the basis of a looser rule.

Splits (`HELD_OUT`): the acceptance rules were developed on the meshes of tests/test_register.py, tests/test_scan*.py
and bench/scan.py's notes (`DEVELOPMENT`); the other twelve are held out.

    python bench/acceptance.py [--split held-out|development|all] [--starts 0,90,180,270] [--table plain] [--masks]
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
WRONG_DEG, WRONG_M = 5.0, 0.02
WEAK = "weak geometry"  # registration's reason for an edge whose pose its evidence pins too loosely
TURN = "ambiguous shape"  # ... for an edge alone placing a frame that one of its turns fits as well (turns.LONE_TURN)
DEVELOPMENT = ("Whey_Protein_Chocolate_12_Packets", "Diet_Pepsi_Soda_Cola12_Pack_12_oz_Cans",
               "Pepsi_Caffeine_Free_Diet_12_CT", "Mattel_SKIP_BO_Card_Game",
               "ReadytoUse_Rolled_Fondant_Pure_White_24_oz_box", "Polar_Herring_Fillets_Smoked_Peppered_705_oz_total",
               "Apples_to_Apples_Kids_Edition", "Google_Cardboard_Original_package",
               "Kotex_U_Barely_There_Liners_Thin_60_count")


def meshes(split: str) -> list[Path]:
    """The shared meshes of a split ("development", "held-out" or "all"), sorted by name."""
    from match import _meshes

    every = _meshes(None)
    if split == "all":
        return every
    dev = [m for m in every if m.name in DEVELOPMENT]
    return dev if split == "development" else [m for m in every if m.name not in DEVELOPMENT]


def run(split: str, starts: list[float], gaps: list[float], table: str, masks: bool) -> dict[float, list[dict]]:
    """{gap: [one record per pair: mesh, start, accepted, reason kind, rotation / translation error, sigma]}."""
    from match import render_views

    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.registration.frames import register_frames
    from gscan.registration.pairwise import RegisterParams

    unbounded = RegisterParams(max_sigma_deg=1e9, max_sigma_rel=1e9)  # every rule but weak geometry

    out: dict[float, list[dict]] = {g: [] for g in gaps}
    for mi, md in enumerate(meshes(split)):
        for s0 in starts:
            views = render_views(md, [s0] + [s0 + g for g in gaps], seed=mi, table_kind=table)
            for gi, g in enumerate(gaps):
                T_gt = inv_T(views[gi + 1][1]) @ views[0][1]
                t0 = time.perf_counter()
                r = register_frames(views[0][0], views[gi + 1][0], RegisterParams(), use_masks=masks)
                seconds = time.perf_counter() - t0
                deg, m = pose_error(r.T_tgt_src, T_gt) if r.T_tgt_src is not None else (np.inf, np.inf)
                why = (r.reason or "accepted").split(" (")[0].split(":")[0]
                # a weak edge again without the bound: would it pass the depth and colour checks?
                rest = why == WEAK and register_frames(views[0][0], views[gi + 1][0], unbounded,
                                                       use_masks=masks).accepted
                out[g].append({"mesh": md.name, "start": s0, "accepted": r.accepted, "deg": deg, "m": m,
                               "why": why, "sigma_deg": r.sigma_deg, "passes_the_rest": rest,
                               "colour": None if r.colour is None else (r.colour.agreeing, r.colour.informative),
                               "seconds": seconds, "turn_seconds": r.timings_ms.get("turns", 0.0) / 1e3})
            print(f"{md.name[:34]:34s} {s0:5.0f}  " + "  ".join(f"{g:.0f}:{_mark(x[-1])}" for g, x in out.items()),
                  file=sys.stderr, flush=True)
    return out


def is_right(r: dict) -> bool:
    """A pair's pose within 5 deg and 2 cm of the ground truth."""
    return bool(r["deg"] < WRONG_DEG and r["m"] < WRONG_M)


def _mark(r: dict) -> str:
    """+ registered right, x registered wrong, . refused."""
    return ("+" if is_right(r) else "x") if r["accepted"] else "."


def report(out: dict[float, list[dict]]) -> None:
    print("| gap | pairs | registered right % | registered wrong | refused as a turn's rival: right / wrong | "
          "refused as weak geometry: right / wrong | "
          "... of which pass every other rule: right / wrong | "
          "weak: sigma claimed / actual rotation error (median) | other refusals |")
    print("|---|---|---|---|---|---|---|---|---|")
    for g, recs in out.items():
        right = [is_right(r) for r in recs]
        acc = [r["accepted"] for r in recs]
        weak = [r for r in recs if r["why"] == WEAK]
        rest = [r for r in weak if r["passes_the_rest"]]
        rest_right = sum(is_right(r) for r in rest)
        w_right = sum(is_right(r) for r in weak)
        ratio = np.median([r["deg"] / r["sigma_deg"] for r in weak if r["sigma_deg"]]) if weak else float("nan")
        claimed = np.median([r["sigma_deg"] for r in weak]) if weak else float("nan")
        turn = [r for r in recs if r["why"] == TURN]
        t_right = sum(is_right(r) for r in turn)
        other = Counter(r["why"] for r in recs if not r["accepted"] and r["why"] not in (WEAK, TURN))
        print(f"| {g:.0f} deg | {len(recs)} | {100 * np.mean(np.logical_and(acc, right)):.0f} | "
              f"{int(np.sum(np.logical_and(acc, np.logical_not(right))))} | {t_right} / {len(turn) - t_right} | "
              f"{w_right} / {len(weak) - w_right} | "
              f"{rest_right} / {len(rest) - rest_right} | "
              f"{claimed:.1f} deg, error {ratio:.1f} x sigma | "
              + ", ".join(f"{k} {v}" for k, v in other.most_common()) + " |")
    for g, recs in out.items():
        rest = sorted((r for r in recs if r["passes_the_rest"]), key=lambda r: r["sigma_deg"])
        if rest:  # could any bound on the claimed sigma separate the right from the wrong?
            print(f"weak, passing every other rule, at {g:.0f} deg (sigma claimed: error): " + ", ".join(
                f"{r['sigma_deg']:.2f}: {r['deg']:.1f} deg / {1000 * r['m']:.0f} mm" for r in rest))
        for r in recs:
            if r["why"] == TURN and not is_right(r):
                print(f"refused as a turn's rival at {g:.0f} deg (registered wrong without that rule): "
                      f"{r['mesh']} from {r['start']:.0f} deg, {r['deg']:.1f} deg / {1000 * r['m']:.0f} mm off")
            if r["accepted"] and not is_right(r):
                print(f"registered wrong at {g:.0f} deg: {r['mesh']} from {r['start']:.0f} deg, {r['deg']:.1f} deg / "
                      f"{1000 * r['m']:.0f} mm off, sigma {r['sigma_deg']:.2f} deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", default="held-out", choices=("held-out", "development", "all"))
    ap.add_argument("--starts", default="0,90,180,270", metavar="AZ,..")
    ap.add_argument("--gaps", default="20,60,120")
    ap.add_argument("--table", default="plain", choices=("newspaper", "wood", "fabric", "plain"))
    ap.add_argument("--masks", action="store_true", help="the object's pixels only (a moving object's scan)")
    a = ap.parse_args()
    t0 = time.time()
    out = run(a.split, [float(x) for x in a.starts.split(",")], [float(x) for x in a.gaps.split(",")], a.table,
              a.masks)
    print(f"\n{a.split} split, {a.table} table, {'object pixels' if a.masks else 'whole frames'}, starts {a.starts}: "
          f"{time.time() - t0:.0f} s")
    report(out)
    every = [r for rs in out.values() for r in rs]
    print(f"time per pair (register_frames): median {np.median([r['seconds'] for r in every]):.3f} s, of which "
          f"the turn rule median {np.median([r['turn_seconds'] for r in every]):.3f} s (max "
          f"{max(r['turn_seconds'] for r in every):.2f} s); the turn rule's share of the total "
          f"{sum(r['turn_seconds'] for r in every) / sum(r['seconds'] for r in every):.0%}")


if __name__ == "__main__":
    main()
