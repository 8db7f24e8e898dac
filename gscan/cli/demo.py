"""`gscan demo`: scan the bundled sample, estimate its held-back frames, open the viewer."""
from __future__ import annotations

from pathlib import Path

import typer

from gscan.cli.imports import SCAN_IMPORTS, import_holding_ctrl_c
from gscan.cli.output import err, say, setup_logging
from gscan.cli.scan import print_scan_summary


def demo(
    no_view: bool = typer.Option(False, "--no-view", help="do not open the viewer at the end"),
    output: Path = typer.Option(Path("demo-output"), "-o", "--output", help="folder for the demo's template"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="viewer port"),
) -> None:
    """Scan the bundled sample, estimate its held-back frames, then open the viewer."""
    setup_logging(False)  # warnings on stderr, the first run's "compiling the numeric kernels" among them
    import_holding_ctrl_c(*SCAN_IMPORTS)
    from rich.table import Table

    from gscan.demo import SAMPLES, check_demo_output, evaluate_sample, scan_sample
    from gscan.progress import RichProgress

    check_demo_output(output)  # before the first step is announced: only the demo's own template is replaced

    say(("1/3 scanning", "bold"), f" {SAMPLES / 'capture'} -> {output / 'sample.gscan'}")
    with RichProgress(err) as progress:
        result = scan_sample(output, progress)
    print_scan_summary(result)
    say(("2/3 estimating", "bold"), " the held-back frames")
    table = Table(title="pose estimation on held-back frames (errors against ground truth)")
    for col in ("frame", "found", "rot err (deg)", "trans err (mm)", "ADD (mm)", "GMatch pairs", "time (ms)"):
        table.add_column(col, justify="right")
    held = evaluate_sample(result.output)
    for r in held:
        table.add_row(r.name, "yes" if r.found else "no", f"{r.rot_err_deg:.2f}", f"{r.trans_err_mm:.1f}",
                      f"{r.add_mm:.1f}", str(r.n_matches), f"{r.total_ms:.0f}")
    err.print(table)
    found = [r for r in held if r.found]
    worst = "" if not found else (f"; largest errors {max(r.rot_err_deg for r in found):.2f} deg, "
                                  f"{max(r.trans_err_mm for r in found):.1f} mm, "
                                  f"ADD {max(r.add_mm for r in found):.1f} mm")
    say(f"held-back frames: {len(found)}/{len(held)} found{worst}")
    if no_view:
        say(("3/3", "bold"), f" viewer skipped; run `gscan view {result.output}`")
        return
    from gscan.viewer.app import run_viewer

    say(("3/3 viewer", "bold"))
    run_viewer(result.output, port=port,
               on_ready=lambda url: say("viewer ready at ", (url, "bold"), " (Ctrl+C to stop)"))
