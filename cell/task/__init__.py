"""The inspection task as typed values in SI units: the schema engine (`schema`), the task and
material files' loader (`loader`), the task types (`types`), the device settings of its `cell`
section (`device_config`) and the ChArUco board (`board`).

Layer 3: imports `cell.core` and `cell.physics`."""
