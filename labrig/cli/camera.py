"""File conversion commands: ``labrig import`` (Prophesee .raw / Metavision .hdf5, or a ROS 2 bag -> labrig
recording) and ``labrig export`` (recording -> EVT3 .raw that Prophesee tools read, or a recording or a
pipeline result -> ROS 2 bag).

Mount on the main app with :func:`add_camera_commands`; the work is in :mod:`labrig.recording.convert`,
:mod:`labrig.recording.ros2` (recordings and bags) and :mod:`labrig.pipeline.ros2_result` (results to bags).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import TextColumn, TimeElapsedColumn, TimeRemainingColumn

from labrig.cli.console import IndentersOption, JsonOption, console, err_console, print_json, progress_bar
from labrig.errors import LabrigError

if TYPE_CHECKING:
    from labrig.recording.ros2.bag_import import BagTopics

OverwriteOption = Annotated[bool, typer.Option("--overwrite", help="Replace the output file if it exists.")]


@contextmanager
def _progress(description: str, disabled: bool) -> Iterator[Callable[[int, int, str], None]]:
    """A transient bar on a terminal (none with --json); yields the conversion's progress callback."""
    with progress_bar(TextColumn("{task.completed:,.0f}/{task.total:,.0f} {task.fields[unit]}"), TimeElapsedColumn(),
                      TimeRemainingColumn(), disable=disabled or not err_console.is_terminal, transient=True) as bar:
        task = None

        def update(done: int, total: int, unit: str) -> None:
            nonlocal task
            if task is None:
                task = bar.add_task(description, total=total, unit=unit)
            bar.update(task, completed=done)

        yield update


def import_command(
    file: Annotated[Path, typer.Argument(help=(
        "Prophesee RAW (.raw, EVT 3.0 / 2.0), Metavision HDF5 (.hdf5), or a ROS 2 bag (an .mcap file or a bag folder)."))],
    output: Annotated[Path, typer.Argument(help="labrig recording to write (.h5).")],
    events: Annotated[str | None, typer.Option(help=(
        "Bag: the camera's event_camera_msgs/msg/EventPacket topic (evt3 or mono; default: the bag's only one)."))] = None,
    wrench: Annotated[str | None, typer.Option(help=(
        "Bag: the F/T sensor's geometry_msgs/msg/WrenchStamped topic (default: the bag's only one, if any)."))] = None,
    pose: Annotated[str | None, typer.Option(help=(
        "Bag: the tool's pose in the machine frame: a PoseStamped or TransformStamped topic (default: the bag's only "
        "one, if any), or a tf2_msgs/msg/TFMessage topic such as /tf with --pose-frame."))] = None,
    pose_frame: Annotated[str | None, typer.Option(help=(
        "Bag: the tool's child frame (child_frame_id) among --pose's transforms (default: their only one)."))] = None,
    cnc_status: Annotated[str | None, typer.Option(help=(
        "Bag: labrig_msgs/msg/CncStatus topic, the CNC's state and feed (default: the bag's only one)."))] = None,
    gcode: Annotated[str | None, typer.Option(help=(
        "Bag: labrig_msgs/msg/GcodeLine topic, the CNC's G-code conversation (default: the bag's only one)."))] = None,
    phases: Annotated[str | None, typer.Option(help="Bag: labrig_msgs/msg/Phase topic (default: the bag's only one).")
                      ] = None,
    triggers: Annotated[str | None, typer.Option(help=(
        "Bag: an EventPacket topic in the 'trigger' encoding (older drivers): the camera's trigger edges."))] = None,
    trigger_out: Annotated[str | None, typer.Option(help=(
        "Bag: labrig_msgs/msg/TriggerEdge topic (edges sent to the camera; default: the bag's only one)."))] = None,
    indenter: Annotated[str | None, typer.Option(help=(
        "Bag: the indenter the run used, by name in --indenters (a labrig bag names its own); groundtruth needs it."))
    ] = None,
    indenters: IndentersOption = None,
    rig: Annotated[Path | None, typer.Option(help="Bag: the rig file to store with the recording (groundtruth reads it).")
                   ] = None,
    max_gap_s: Annotated[float, typer.Option(help=(
        "Bag: the longest silence between a topic's stamps, s, before it counts as a clock gap."))] = 1.0,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Import a camera file or a ROS 2 bag into a labrig recording."""
    from labrig.recording.ros2.bag_import import BagTopics
    from labrig.recording.ros2.bagfile import is_bag

    wanted = BagTopics(events=events, wrench=wrench, pose=pose, phases=phases, triggers=triggers, trigger_out=trigger_out,
                       cnc_status=cnc_status, gcode=gcode, pose_frame=pose_frame)
    bag_options = {"--events": events, "--wrench": wrench, "--pose": pose, "--pose-frame": pose_frame,
                   "--cnc-status": cnc_status, "--gcode": gcode, "--phases": phases, "--triggers": triggers,
                   "--trigger-out": trigger_out, "--indenter": indenter, "--indenters": indenters, "--rig": rig}
    if is_bag(file):
        _import_bag(file, output, wanted, indenter, indenters, rig, max_gap_s, overwrite, as_json)
        return
    if given := [flag for flag, value in bag_options.items() if value is not None]:
        raise LabrigError(f"{', '.join(given)} apply to a ROS 2 bag (an .mcap file or a bag folder); {file} is not one")
    from labrig.recording.convert import import_file

    with _progress(f"import {file.name}", as_json) as progress:
        summary = import_file(file, output, overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    rate = summary.events / summary.elapsed_s / 1e6 if summary.elapsed_s > 0 else 0.0
    console.print(
        f"[green]imported[/] {summary.events:,} events and {summary.triggers} trigger edges "
        f"({summary.duration_s:.3f} s of {summary.source_format}) into {output} "
        f"in {summary.elapsed_s:.2f} s ({rate:.1f} Mev/s)",
        highlight=False,
    )
    if summary.skipped_words:
        console.print(f"[yellow]warning:[/] {summary.skipped_words} words of the RAW payload were not decoded")


def _import_bag(bag: Path, output: Path, wanted: BagTopics, indenter: str | None, indenters: Path | None,
                rig: Path | None, max_gap_s: float, overwrite: bool, as_json: bool) -> None:
    from labrig.recording.ros2.bag_import import LabInputs, import_bag

    lab = LabInputs()
    if indenter is not None:
        from labrig.indenters import DEFAULT_INDENTERS, indenter_toml, load_indenter

        chosen = load_indenter(indenter, indenters or DEFAULT_INDENTERS)
        lab = LabInputs(indenter=indenter, indenter_toml=indenter_toml(chosen))
    elif indenters is not None:
        raise LabrigError("--indenters names the file --indenter looks in; give --indenter too")
    if rig is not None:
        from labrig.config import load_rig

        load_rig(rig)  # a bad rig file is one line now, not at groundtruth
        lab = LabInputs(lab.indenter, lab.indenter_toml, rig.read_text())
    with _progress(f"import {bag.name}", as_json) as progress:
        summary = import_bag(bag, output, wanted, lab=lab, max_gap_s=max_gap_s, overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    console.print(
        f"[green]imported[/] {summary.events:,} events ({summary.event_encoding}), {summary.triggers} trigger edges, "
        f"{summary.wrenches:,} wrenches, {summary.poses:,} poses ({summary.cnc_status:,} CNC status reports), "
        f"{summary.gcode_lines:,} G-code lines and {summary.phases} phases ({summary.duration_s:.3f} s) from {bag} "
        f"into {output} in {summary.elapsed_s:.2f} s",
        highlight=False,
    )
    for stream, topic in summary.topics.items():
        console.print(f"  {stream}: {topic}", highlight=False)
    for warning in summary.warnings:
        console.print(f"[yellow]warning:[/] {warning}")
    if summary.skipped_words:
        console.print(f"[yellow]warning:[/] {summary.skipped_words} EVT 3.0 words of {summary.topics['events']} were not decoded")


def export_command(
    recording: Annotated[Path, typer.Argument(help="labrig recording (.h5), or a pipeline result (labrig run --out) for --bag.")],
    raw: Annotated[Path | None, typer.Option("--raw", help="Write the events as an EVT 3.0 RAW file here.")] = None,
    bag: Annotated[Path | None, typer.Option("--bag", help=(
        "Write a ROS 2 bag here: OUT.mcap (one MCAP file) or a bag folder (any other name)."))] = None,
    packet_ms: Annotated[float, typer.Option(help=(
        "--bag: host time one camera packet gathers, ms (the Metavision driver publishes every 1 ms or more)."))] = 2.0,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Export a recording's camera events and trigger edges as an EVT 3.0 .raw (readable by Prophesee tools), or a
    recording or a pipeline result as a ROS 2 bag (docs/ros2.md)."""
    if (raw is None) == (bag is None):
        raise LabrigError("give one of --raw OUT.raw (the events for Prophesee tools) or --bag OUT.mcap (a ROS 2 bag)")
    if bag is not None:
        _export_bag(recording, bag, packet_ms, overwrite, as_json)
        return
    assert raw is not None
    from labrig.recording.convert import export_raw

    with _progress(f"export {recording.name}", as_json) as progress:
        summary = export_raw(recording, raw, overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    console.print(
        f"[green]exported[/] {summary.events:,} events and {summary.triggers} trigger edges to {raw} "
        f"({summary.output_bytes / 1e6:.1f} MB, {summary.bytes_per_event:.2f} B/event)",
        highlight=False,
    )


def _export_bag(source: Path, bag: Path, packet_ms: float, overwrite: bool, as_json: bool) -> None:
    from labrig.pipeline.results import is_result_file

    if is_result_file(source):
        from labrig.pipeline.ros2_result import export_result_bag

        with _progress(f"export {source.name}", as_json) as progress:
            result = export_result_bag(source, bag, overwrite=overwrite, progress=progress)
        if as_json:
            print_json(asdict(result))
            return
        console.print(f"[green]exported[/] {result.windows:,} windows (force field, net force, depth, tracks) to {bag} "
                      f"({result.output_bytes / 1e6:.1f} MB)", highlight=False)
        return
    from labrig.recording.ros2.bag_export import export_bag

    with _progress(f"export {source.name}", as_json) as progress:
        summary = export_bag(source, bag, packet_us=round(packet_ms * 1000), overwrite=overwrite, progress=progress)
    if as_json:
        print_json(asdict(summary))
        return
    console.print(
        f"[green]exported[/] {summary.events:,} events in {summary.event_packets:,} EVT 3.0 packets "
        f"({summary.packet_ms_mean:.1f} ms each), {summary.wrenches:,} wrenches, {summary.poses:,} poses with the CNC's "
        f"state and feed, {summary.gcode_lines:,} G-code lines and {summary.phases} phases to {bag} "
        f"({summary.output_bytes / 1e6:.1f} MB)",
        highlight=False,
    )


def add_camera_commands(app: typer.Typer) -> None:
    """Mount ``import`` and ``export`` on the main app."""
    app.command("import")(import_command)
    app.command("export")(export_command)
