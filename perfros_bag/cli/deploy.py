"""``perfros-bag deploy PLAN APP.launch --space space.yaml --out DIR``: run a plan here, validate it."""

from __future__ import annotations

from pathlib import Path

import typer

from perfros_bag.cli._app import command, err, out


@command("deploy", interrupted="interrupted: nothing is left running")
def deploy_cmd(
    plan: Path = typer.Argument(..., metavar="PLAN", help="plan.json from solve."),  # noqa: B008
    launch: Path = typer.Argument(..., metavar="APP.launch", help="Your ROS 1 launch file."),  # noqa: B008
    space: Path = typer.Option(  # noqa: B008
        ..., "--space", help="The space.yaml of the sweep: how each node's value reaches the launch file."),
    out_dir: Path = typer.Option(  # noqa: B008
        ..., "--out", "-o", help="Folder for run.bag, run.cpu.csv, validation.json, deploy.json."),
    duration: float | None = typer.Option(
        None, "--duration", "-d", help="Seconds recorded (default: space.yaml's duration_s)."),
    units_per_core: float = typer.Option(100.0, "--units-per-core", help="CPU units of one core (init drafts 100)."),
    cap: bool = typer.Option(True, "--cap/--no-cap", help="Cap each computer's cgroup at its capacity."),
    tolerance: float | None = typer.Option(
        None, "--tolerance", help="Largest overall deviation in % that passes (exit 0)."),
    net: bool = typer.Option(True, "--net/--no-net",
                             help="Emulate the system's links: each computer a network namespace, "
                                  "each link a veth shaped with tc to its bandwidth (root)."),
    system: Path | None = typer.Option(  # noqa: B008
        None, "--system", help="The plan's system.yaml (default: the one the plan was solved from)."),
) -> None:
    """Run PLAN on this machine (capped cgroups, shaped links), record it and validate it (eq 10)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from perfros_bag.cli.validate import render
    from perfros_bag.sweep.deploy import deploy

    with Progress(TextColumn("deploy"), BarColumn(), TimeElapsedColumn(), TextColumn("{task.description}"),
                  console=err, transient=True) as progress:
        task = progress.add_task("", total=1.0)

        def show(stage: str, frac: float) -> None:
            progress.update(task, completed=frac, description=stage)

        result = deploy(plan, launch, space, out_dir, duration=duration, units_per_core=units_per_core, cap=cap,
                        tolerance=tolerance, net=net, system_path=system, progress=show)
    render(result.validation, out)
    if result.record["forced"]:
        err.print("plan: forced (plan.json \"forced\": true): deployed beyond its computers on purpose",
                  highlight=False)
    capped, network = result.record["cpu_cap"], result.record["network"]
    err.print(f"links: {network['mode']}{' (' + network['reason'] + ')' if network['reason'] else ''}", highlight=False)
    for link in network["links_measured"]:
        err.print(f"  link {link['from']} -> {link['to']}: {link['sent_kBps']:.1f} of {link['shaped_kBps']:.1f} kB/s, "
                  f"{link['drops']} packets dropped", highlight=False)
    err.print(f"cpu cap: {capped['mode']}{' (' + capped['reason'] + ')' if capped['reason'] else ''}; "
              f"wrote {out_dir}/run.bag, run.cpu.csv, validation.json, deploy.json", highlight=False)
    if not result.validation.passed:
        raise typer.Exit(1)
