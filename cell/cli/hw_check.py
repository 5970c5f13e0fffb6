"""`cell hw-check TASK [--json]`: connect to each real device of the task's `cell` section, read and
print its state, move and set nothing; exit 0 when every device answered and reports nothing a
run would stop on, 3 otherwise (each such device named with its address), 2 for bad input."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from cell.core import jsonio
from cell.run.backends import check_hw_devices
from cell.task.loader import load_task


def _rounded(values, decimals):
    return (np.round(values, decimals) + 0.0).tolist()            # + 0.0: no "-0.0"


def _deg(values):
    return str(_rounded(np.degrees(values), 2))


def _arm(s):
    remote = {True: "yes", False: "NO", None: "unknown"}[s["remote_control"]]
    pose = _rounded(s["tcp_pose"], 4)
    return [f"robot mode {s['robot_mode']}, safety mode {s['safety_mode']}, remote control {remote}",
            f"{s['polyscope_version']}, serial number {s['serial_number']}",
            f"TCP pose {pose[:3]} m, rotation vector {pose[3:]} rad (base frame, the controller's active TCP)",
            f"joints {_deg(s['joints_rad'])} deg"]


def _joint(servo):
    if "joint_rad" in servo:
        return f" = {np.degrees(servo['joint_rad']):.2f} deg"
    return f" = {1e3 * servo['joint_m']:.1f} mm" if "joint_m" in servo else ""


def _pan_tilt(s):
    lines = [f"{s['baud']} baud, Protocol 2.0"]
    for dxl_id, servo in s["servos"].items():
        name = f"servo {dxl_id} ({servo['role']})"
        if "error" in servo:
            lines.append(f"{name}: {servo['error']}")
            continue
        lines.append(
            f"{name}: {servo['model']} (model {servo['model_number']}, firmware {servo['firmware']}), "
            f"operating mode {servo['operating_mode']}, torque {'on' if servo['torque_enabled'] else 'off'}, "
            f"position {servo['present_position_ticks']} ticks{_joint(servo)}, limits "
            f"{servo['min_position_limit_ticks']}..{servo['max_position_limit_ticks']} ticks, "
            f"hardware error {servo['hardware_error']}, {servo['temperature_c']} C "
            f"(limit {servo['temperature_limit_c']} C), {servo['input_voltage_v']:.1f} V")
    return lines


def _camera(s):
    def known(value, show=str):
        return "unknown" if value is None else show(value)
    exposure = known(s.get("exposure_s"), lambda t: f"{t * 1e3:.3g} ms")
    span = known(s.get("exposure_range_s"), lambda r: f"{r[0] * 1e3:.3g}..{r[1] * 1e3:.3g} ms")
    return [f"model {known(s.get('model'))}, {s.get('backend', 'backend unknown')}",
            f"{s['width_px']} x {s['height_px']} px, {s['channels']} channel(s), {s['bit_depth']} bit, "
            f"pixel format {known(s.get('pixel_format'))}, exposure {exposure}, range {span}"]


def _lighting(s):
    levels = ", ".join(f"{channel}: {level:.3f}" for channel, level in s["levels"].items())
    return [f"firmware {s['firmware']}", f"drive levels (0..1) by channel: {levels}"]


DETAILS = {"arm": _arm, "pan-tilt": _pan_tilt, "camera": _camera, "lighting": _lighting}


def _lines(check):
    head = f"{check.device:<9} {check.address}: "
    if check.fault is not None:
        return [head + f"NO ANSWER: {check.fault}"]
    lines = [head + ("answered" if check.ready else "answered, NOT READY")]
    lines += [" " * 10 + line for line in DETAILS[check.device](check.state)]
    lines += [" " * 10 + f"problem: {p}" for p in check.state["problems"]]
    return lines


def command(args: argparse.Namespace) -> int:
    task = load_task(args.task)
    checks = check_hw_devices(task)
    if args.json:
        print(jsonio.dumps({"ready": all(c.ready for c in checks), "devices": [
            {"device": c.device, "address": c.address, "answered": c.fault is None, "ready": c.ready,
             "fault": c.fault, "state": c.state} for c in checks]}, indent=2))
    else:
        for check in checks:
            print("\n".join(_lines(check)))
    failed = [c for c in checks if not c.ready]
    if not failed:
        if not args.json:
            print(f"hw-check: all {len(checks)} devices answered; nothing was moved or set")
        return 0
    for c in failed:
        what = f"did not answer: {c.fault}" if c.fault else "not ready: " + "; ".join(c.problems)
        print(f"cell hw-check: {c.device} at {c.address} {what}", file=sys.stderr, flush=True)
    return 3
