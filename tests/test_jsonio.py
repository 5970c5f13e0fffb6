"""Every JSON file of a run is strict JSON: numpy values plain, non-finite numbers null."""
import json
from pathlib import Path

import numpy as np

from cell.core.jsonio import dumps


def test_numpy_values_are_plain_and_non_finite_numbers_are_null():
    value = {"a": np.float64(np.nan), "b": (1, np.int64(2)), "c": np.array([[1.0, np.inf]]),
             "d": [float("-inf"), "x"], "e": np.bool_(True), "f": Path("runs/x")}
    assert json.loads(dumps(value)) == {"a": None, "b": [1, 2], "c": [[1.0, None]], "d": [None, "x"],
                                        "e": True, "f": "runs/x"}
    assert "NaN" not in dumps(value) and "Infinity" not in dumps(value)
