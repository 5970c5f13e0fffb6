"""Helpers the device, closed-loop and calibration tests share: task variants, device settings
read as load_task reads them, and a simulated cell that records the safe-stop calls its devices
receive, and the pixels of a feature's projected disk."""
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml

from cell.run import inspection, loop

from cell.physics import projection
from cell.task.device_config import SECTIONS, devices_config
from cell.core.errors import CellError
from cell.task.loader import load_task
from cell.planning.scene import build_scene
from cell.task.schema import parse
from sim.cell import make_sim_devices


def variant(tmp_path, source, changes):
    """A copy of a task with {dotted.key: value} changed, its files referenced absolutely."""
    source = Path(source)
    raw = yaml.safe_load(source.read_text())
    for key in ("mesh", "material"):
        raw["part"][key] = str((source.parent / raw["part"][key]).resolve())
    for dotted, value in changes.items():
        *parents, last = dotted.split(".")
        node = raw
        for name in parents:
            node = node.setdefault(name, {})
        node[last] = value
    path = tmp_path / f"{source.stem}-variant.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def device_settings(raw, file="tasks/hinge.yaml", bit_depth=8):
    """DevicesConfig of raw `cell.arm` / `cell.pan_tilt` / `cell.camera` mappings, checked as
    load_task checks a task's `cell` section (camera.sensor.bit_depth: bit_depth)."""
    return devices_config(file, parse(file, "cell", raw, SECTIONS), written=raw, bit_depth=bit_depth)


def record_stops(devices, stops):
    """The devices, every arm.stop, pan-tilt.stop and camera.close they receive appended to stops
    in order."""
    for device, name in ((devices.arm, "stop"), (devices.lamp, "stop"), (devices.camera, "close")):
        method = getattr(device, name)
        setattr(device, name, lambda *a, _m=method, _n=f"{device.device}.{name}", **k:
                (stops.append(_n), _m(*a, **k))[1])
    return devices


def recording_connect(task, cell, faults=None):
    """connect(scene) -> the simulated cell's Devices, stored in cell.devices; every arm.stop,
    pan-tilt.stop and camera.close they receive is appended to cell.stops in order."""
    def connect(scene):
        cell.devices = record_stops(make_sim_devices(task, scene, faults=faults), cell.stops)
        return cell.devices
    return connect


def run_loop(task_path, out):
    """loop.run of a task file on the simulated cell (a whole part's, inspection.run, shot by shot,
    as `cell run` runs it): a namespace of its devices, the stops they received, the error it
    ended with (None), report.json, the log's lines and their steps."""
    task = load_task(task_path)
    cell = SimpleNamespace(devices=None, stops=[], error=None)
    try:
        if task.whole_part:     # the simulated cell renders the first feature's scene, as cell run's
            inspection.run(task, out, recording_connect(task.with_feature(0), cell))
        else:
            loop.run(task, out, recording_connect(task, cell))
    except CellError as err:
        cell.error = err
    cell.report = json.loads((Path(out) / "report.json").read_text())
    cell.log = [json.loads(line) for line in (Path(out) / "log.jsonl").read_text().splitlines()]
    cell.steps = [line["step"] for line in cell.log]
    return cell


def disk_pixels(task, f, T_cell_cam, shape, shrink=1.0):
    """Independent of the loop's hull: the pixels within shrink x feature f's radius of its
    projected centre (the camera looks nearly along the normal: the disk images as a circle)."""
    scene = build_scene(task.with_feature(f), T_cell_cam=T_cell_cam)
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    (centre,), (depth,) = projection.project(K, T_cell_cam, scene.center[None])
    v, u = np.mgrid[:shape[0], :shape[1]]
    return np.hypot(u - centre[0], v - centre[1]) < shrink * K[0, 0] * task.features[f].radius_m / depth
