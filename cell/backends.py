"""The one place that builds the cell's devices: the simulated cell (sim/) or the real one
(cell/hw/), from the task's validated settings."""


def open_devices(task, scene, backend, yes=False):
    """The cell's devices: the simulated cell (rendering `scene`) or, for backend hw, the real
    ones from the task's cell.arm / cell.pan_tilt / cell.camera settings. The sim has no operator
    to set the lamp radius: it confirms for itself."""
    if backend == "hw":
        from cell.devices import devices_from_config, make_hw_devices
        return make_hw_devices(devices_from_config(task.cell.devices, task.path), task, yes=yes)
    from sim.cell import make_sim_devices
    return make_sim_devices(task, scene, yes=True)
