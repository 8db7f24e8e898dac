"""BOP19 scores from gscan against the BOP toolkit's own scorer (thodan/bop_toolkit, scripts/eval_bop19_pose.py).

    python bench/bop_toolkit.py --toolkit /path/to/bop_toolkit --python /tmp/boptk-venv/bin/python
    python bench/bop_toolkit.py --toolkit ... --json out.json --work /tmp/bop-cmp   # keep the files

In a temporary folder: the bundled sample (gscan.demo.SAMPLES / "capture") scanned by `gscan scan`, its
`gscan export --format bop`, and the BOP19 results CSVs of four sets of estimates of its 30 images:
- gscan: the estimates `gscan eval TEMPLATE SCENE --model models_eval/obj_000001.ply` makes, scored by it;
- gt: the ground-truth poses themselves;
- noise5 / noise20: the ground-truth poses moved in the object frame, per image (seeded, --seed): a rotation of
  up to 5 / 20 deg about a random axis and a translation of up to 1 / 3 cm in a random direction (both uniform).
gscan scores the last three with `gscan.evaluate.score_results` (`gscan eval`'s errors and metrics, without
estimating); the toolkit scores all four with eval_bop19_pose.py, run in a subprocess on the same files. Prints
AR, AR VSD, AR MSSD and AR MSPD from each, and their differences (gscan - toolkit).

The toolkit knows datasets by name: it scores the export as a user does, under the name "gscan" that the export's
bop_toolkit.patch registers (docs/exports.md), applied with `git apply` to a copy of the checkout's
bop_toolkit_lib/ and scripts/ (the checkout itself is left as it is). Its VSD renders with its vispy renderer off
screen: EGL through Mesa (llvmpipe, no GPU or display); gscan's ray-casts the same mesh with open3d, sampling each
pixel where OpenGL does (`gscan.evaluate.metrics.VSD_RENDER_PIXEL_OFFSET`).

What the user provides (this script downloads nothing and imports nothing of the toolkit: it only runs it):
- a checkout of https://github.com/thodan/bop_toolkit (`--toolkit`); its patched copy is put on PYTHONPATH;
  git, which applies the patch;
- a Python that runs it (`--python`, default: this one), with the packages its evaluation imports: numpy, scipy,
  imageio, pypng, vispy, PyOpenGL, and Mesa's EGL (Debian: libegl1 libgl1-mesa-dri). gscan's environment plus
  three packages does, e.g.
      python3 -m venv --system-site-packages /tmp/boptk-venv
      /tmp/boptk-venv/bin/pip install pypng vispy pyopengl   # and imageio scipy where that Python lacks them
  (the toolkit's pyproject pins numpy<2; its evaluation runs on numpy 2).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gscan.demo import SAMPLES
from gscan.evaluate import score_results
from gscan.exporters.bop import TOOLKIT_DATASET
from gscan.geometry.transforms import make_T, rotvec_to_R

ROOT = Path(__file__).resolve().parents[1]
DATASET = TOOLKIT_DATASET  # the name the export's bop_toolkit.patch registers it under
NOISE = {"noise5": (5.0, 0.01), "noise20": (20.0, 0.03)}  # name -> (max rotation deg, max translation m)
METRICS = {"AR": "bop19_average_recall", "AR VSD": "bop19_average_recall_vsd",
           "AR MSSD": "bop19_average_recall_mssd", "AR MSPD": "bop19_average_recall_mspd"}
HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def gscan_cli(*args: str | Path) -> subprocess.CompletedProcess:
    """`python -m gscan.cli ARGS` from the repository root; exits with its message when it fails."""
    r = subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, check=False)
    if r.returncode != 0:
        sys.exit(f"gscan {args[0]} failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return r


def ground_truth(scene: Path, obj_id: int = 1) -> dict[int, np.ndarray]:
    """{im_id: T_cam_obj [4 x 4] in metres} of `obj_id`, read from the scene's scene_gt.json."""
    out = {}
    for im, insts in json.loads((scene / "scene_gt.json").read_text()).items():
        for g in insts:
            if g["obj_id"] == obj_id:
                T = np.eye(4)
                T[:3, :3] = np.reshape(g["cam_R_m2c"], (3, 3))
                T[:3, 3] = np.asarray(g["cam_t_m2c"], dtype=np.float64) / 1000.0
                out[int(im)] = T
    return dict(sorted(out.items()))


def perturbed(gt: dict[int, np.ndarray], max_deg: float, max_m: float, seed: int) -> dict[int, np.ndarray]:
    """Each pose moved in the object frame: T @ dT, dT a rotation of U(0, max_deg) about a uniformly random axis
    and a translation of U(0, max_m) in a uniformly random direction (one seeded generator, images in order)."""
    rng = np.random.default_rng(seed)
    out = {}
    for im, T in gt.items():
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        rot = axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.0, max_deg))
        out[im] = T @ make_T(rotvec_to_R(rot), direction / np.linalg.norm(direction) * rng.uniform(0.0, max_m))
    return out


def write_results(path: Path, poses: dict[int, np.ndarray], scene_id: int = 1, obj_id: int = 1) -> None:
    """A BOP19 results CSV of `poses` (score 1, time -1: not measured)."""
    lines = [HEADER]
    for im, T in poses.items():
        R = " ".join(f"{x:.9g}" for x in T[:3, :3].reshape(-1))
        t = " ".join(f"{x:.6f}" for x in T[:3, 3] * 1000.0)
        lines.append(f"{scene_id},{im},{obj_id},1.000000,{R},{t},-1")
    path.write_text("\n".join(lines) + "\n")


def patched_toolkit(toolkit: Path, export: Path, work: Path) -> Path:
    """work/bop_toolkit: a copy of the checkout's bop_toolkit_lib/ and scripts/ (not its tests' data) with the
    export's bop_toolkit.patch applied by `git apply`, as a user applies it; RuntimeError with git's message when
    the patch does not apply."""
    dst = work / "bop_toolkit"
    for sub in ("bop_toolkit_lib", "scripts"):
        shutil.copytree(toolkit / sub, dst / sub, ignore=shutil.ignore_patterns("tests", "__pycache__"))
    r = subprocess.run(["git", "apply", str(export / "bop_toolkit.patch")], cwd=dst, capture_output=True, text=True,
                       check=False)
    if r.returncode != 0:
        raise RuntimeError(f"{export / 'bop_toolkit.patch'} does not apply to {toolkit}: {r.stderr.strip()}")
    return dst


def run_toolkit(toolkit: Path, python: Path, bop_path: Path, results: Path, names: list[str], work: Path,
                renderer: str) -> dict[str, tuple[dict[str, float], dict[int, dict]]]:
    """eval_bop19_pose.py on the results files `names` (in `results`): {name: ({metric: percent}, its per-image
    errors as `toolkit_errors` reads them)}. Its scripts start their steps as `python ...`: a `python` on PATH
    that runs `python`."""
    bin_dir = work / "bin"
    bin_dir.mkdir(exist_ok=True)
    wrapper = bin_dir / "python"
    wrapper.write_text(f'#!/bin/sh\nexec "{python}" "$@"\n')
    wrapper.chmod(0o755)
    eval_path = work / "toolkit_eval"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(toolkit),
           "BOP_PATH": str(bop_path), "BOP_RESULTS_PATH": str(results), "BOP_EVAL_PATH": str(eval_path)}
    env.setdefault("EGL_PLATFORM", "surfaceless")  # Mesa's EGL without a display
    cmd = [str(wrapper), str(toolkit / "scripts" / "eval_bop19_pose.py"), f"--renderer_type={renderer}",
           f"--result_filenames={','.join(names)}", f"--results_path={results}", f"--eval_path={eval_path}",
           "--num_workers=1"]
    log = work / "toolkit.log"
    with log.open("w") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=toolkit, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"the BOP toolkit failed ({r.returncode}); the end of {log}:\n{log.read_text()[-3000:]}")
    out = {}
    for name in names:
        scores = json.loads((eval_path / Path(name).stem / "scores_bop19.json").read_text())
        out[name] = ({k: 100.0 * float(scores[v]) for k, v in METRICS.items()},
                     toolkit_errors(eval_path / Path(name).stem))
    return out


def toolkit_errors(folder: Path) -> dict[int, dict]:
    """{im_id: {"mssd": mm, "mspd": px, "vsd": [one per tau, ascending]}} from the toolkit's errors files of one
    results file (folders error=mssd_..., error=mspd_..., error=vsd_..._tau=T; the one ground-truth instance)."""
    out: dict[int, dict] = {}
    vsd_dirs = sorted(folder.glob("error=vsd_*"), key=lambda d: float(d.name.rsplit("tau=", 1)[1]))
    for kind, dirs in (("mssd", list(folder.glob("error=mssd_*"))), ("mspd", list(folder.glob("error=mspd_*"))),
                       ("vsd", vsd_dirs)):
        for d in dirs:
            for e in json.loads(next(d.glob("errors_*.json")).read_text()):
                err = float(e["errors"]["0"][0])
                row = out.setdefault(int(e["im_id"]), {"vsd": []})
                if kind == "vsd":
                    row["vsd"].append(err)
                else:
                    row[kind] = err
    return out


def gscan_errors(rows: list[dict]) -> dict[int, dict]:
    """The same per-image errors from gscan's report rows (EvalRow.to_json(): metres -> mm)."""
    return {int(r["im_id"]): {"mssd": 1000.0 * r["mssd_m"], "mspd": r["mspd_px"], "vsd": list(r["vsd"])}
            for r in rows}


def largest_differences(ours: dict[int, dict], theirs: dict[int, dict]) -> dict[str, float]:
    """Over the images both scored: the largest |gscan - toolkit| of MSSD (mm), MSPD (px) and VSD (any tau)."""
    ims = sorted(set(ours) & set(theirs))
    assert len(ims) == len(ours) == len(theirs), "gscan and the toolkit scored different images"
    return {"MSSD mm": max(abs(ours[i]["mssd"] - theirs[i]["mssd"]) for i in ims),
            "MSPD px": max(abs(ours[i]["mspd"] - theirs[i]["mspd"]) for i in ims),
            "VSD": max(float(np.max(np.abs(np.subtract(ours[i]["vsd"], theirs[i]["vsd"])))) for i in ims)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--toolkit", type=Path, required=True, help="a checkout of github.com/thodan/bop_toolkit")
    ap.add_argument("--python", type=Path, default=Path(sys.executable),
                    help="the Python that runs the toolkit (default: this one)")
    ap.add_argument("--renderer", default="vispy", help="the toolkit's renderer for VSD (vispy, cpp, python)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the perturbed estimates")
    ap.add_argument("--work", type=Path, help="folder for the files (kept; default: a temporary folder, removed)")
    ap.add_argument("--json", type=Path, help="write the figures to this JSON file")
    args = ap.parse_args()
    toolkit = args.toolkit.resolve()
    if not (toolkit / "scripts" / "eval_bop19_pose.py").is_file():
        sys.exit(f"{toolkit}: not a checkout of the BOP toolkit (no scripts/eval_bop19_pose.py)")
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=False)
        work = args.work.resolve()
    else:
        work = Path(tempfile.mkdtemp(prefix="gscan-bop-toolkit-"))
    try:
        report = compare(toolkit, args.python, work, args.renderer, args.seed)
    except RuntimeError as e:
        sys.exit(str(e))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print_table(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


def compare(toolkit: Path, python: Path, work: Path, renderer: str, seed: int) -> dict:
    template, export, results = work / "sample.gscan", work / "datasets" / DATASET, work / "results"
    results.mkdir()
    t0 = time.perf_counter()
    gscan_cli("scan", SAMPLES / "capture", "-o", template, "--json")
    gscan_cli("export", template, "--format", "bop", "-o", export)
    scene, model = export / "test" / "000001", export / "models_eval" / "obj_000001.ply"
    t_build = time.perf_counter() - t0
    names = {"gscan": f"gscan_{DATASET}-test.csv", "gt": f"gt_{DATASET}-test.csv"}
    t0 = time.perf_counter()
    js = json.loads(gscan_cli("eval", template, scene, "-o", results / names["gscan"], "--model", model,
                              "--json").stdout)
    t_eval = time.perf_counter() - t0
    gscan = {"gscan": ({k: float(js["metrics"][k]) for k in METRICS}, gscan_errors(js["rows"]))}
    gt = ground_truth(scene)
    write_results(results / names["gt"], gt)
    for i, (name, (deg, m)) in enumerate(NOISE.items()):
        names[name] = f"{name}_{DATASET}-test.csv"
        write_results(results / names[name], perturbed(gt, deg, m, seed + i))
    t0 = time.perf_counter()
    for name in names:
        if name != "gscan":
            rep = score_results(results / names[name], scene, model)
            gscan[name] = ({k: float(rep.metrics[k]) for k in METRICS}, gscan_errors([r.to_json() for r in rep.rows]))
    t_score = time.perf_counter() - t0
    patched = patched_toolkit(toolkit, export, work)
    t0 = time.perf_counter()
    tk = run_toolkit(patched, python.absolute(), export.parent, results, list(names.values()), work, renderer)
    t_toolkit = time.perf_counter() - t0
    return {"images": len(gt), "seed": seed, "noise": {k: {"max_deg": d, "max_m": m} for k, (d, m) in NOISE.items()},
            "seconds": {"scan + export": t_build, "gscan eval (estimate + score)": t_eval,
                        "gscan score_results (3 sets)": t_score, "toolkit (4 sets)": t_toolkit},
            "sets": {name: {"gscan": gscan[name][0], "toolkit": tk[file][0],
                            "largest per-image difference": largest_differences(gscan[name][1], tk[file][1])}
                     for name, file in names.items()}}


def print_table(report: dict) -> None:
    cols = list(METRICS)
    print(f"{report['images']} images; per metric: gscan / BOP toolkit / difference (percent)")
    print("| estimates | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for name, s in report["sets"].items():
        cells = [f"{s['gscan'][k]:.3f} / {s['toolkit'][k]:.3f} / {s['gscan'][k] - s['toolkit'][k]:+.3f}" for k in cols]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("largest per-image |gscan - toolkit|:")
    for name, s in report["sets"].items():
        print(f"  {name}: " + ", ".join(f"{k} {v:.2g}" for k, v in s["largest per-image difference"].items()))
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in report["seconds"].items()))


if __name__ == "__main__":
    main()
