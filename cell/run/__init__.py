"""`cell run`: the cell driven in a closed loop. Devices built for a backend (`backends`: the
simulated cell of `sim` or the real adapters), plans recorded and the cell moved and captured
(`acquisition`), the feature found in the capture (`registration`) and measured (`measurement`),
the control law (`control`), the material refitted (`refit`), the closed loop of one shot, of one
feature or several (`loop`, its steps sharing a `context`), and a run of several shots
(`inspection`) in the order `route` gives.

Layer 8: imports the layers below, `kernels` and, in `backends` only, `sim`."""
