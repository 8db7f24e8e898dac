"""The typer application: its global options and the commands of each module, registered in the order `--help`
lists them (`gscan.cli.entry.main` runs it)."""
from __future__ import annotations

import sys

import typer

from gscan.cli.batch import batch, batch_eval, eval_cmd
from gscan.cli.capture import capture
from gscan.cli.demo import demo
from gscan.cli.estimate import estimate, track
from gscan.cli.ros2 import ROS2_CONTEXT, ros2
from gscan.cli.scan import config_dump, scan, template_from_mesh
from gscan.cli.service import serve
from gscan.cli.template import export, grasp_add, grasp_list, info, poses
from gscan.cli.view import view

# rich_markup_mode=None: click's plain help, which wraps the help text and never cuts an option's name or its
# choice list (typer's boxed layout cuts both in a narrow terminal)
app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, no_args_is_help=True, rich_markup_mode=None,
                  help="Scan objects with an RGB-D camera into GMatch templates; estimate their 6DoF pose on a CPU.")
grasp_app = typer.Typer(no_args_is_help=True, help="Named grasp poses stored in a template (object frame).")
config_app = typer.Typer(no_args_is_help=True, help="Scan and estimator configuration.")
app.add_typer(grasp_app, name="grasp")
app.add_typer(config_app, name="config")

app.command()(scan)
app.command("template-from-mesh")(template_from_mesh)
app.command()(estimate)
app.command()(track)
app.command()(poses)
app.command()(info)
app.command()(export)
app.command()(view)
app.command()(serve)
app.command(context_settings=ROS2_CONTEXT)(ros2)
grasp_app.command("add")(grasp_add)
grasp_app.command("list")(grasp_list)
app.command("eval")(eval_cmd)
app.command()(batch)
app.command("batch-eval")(batch_eval)
config_app.command("dump")(config_dump)
app.command()(capture)
app.command()(demo)


def _version(value: bool) -> None:
    if value:
        from gscan._version import __version__

        sys.stdout.write(f"gscan {__version__}\n")
        raise typer.Exit()


@app.callback()
def _main_options(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="print the version and exit"),
) -> None:
    """Scan objects with an RGB-D camera into GMatch templates; estimate their 6DoF pose on a CPU."""
    # every command is a process gscan owns: one BLAS / OpenMP thread unless the environment names a count (the
    # rule and its reasons: gscan.threads); `main` applied it before the commands loaded, this is for `app()` run
    # from Python
    from gscan.threads import one_blas_thread

    one_blas_thread()
