"""to_plain gives YAML-safe Python values, fresh lists, for numpy arrays of any kind and plain lists."""
from pathlib import Path

import numpy as np

from gls_calibration.common.files import to_plain


def _types(value):
    """Every type inside ``value`` (containers included)."""
    found = {type(value)}
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found |= {type(key)} | _types(item)
    return found


def test_arrays_lists_and_scalars_become_plain_python():
    numbers = [1.0, "s", None, True, 3]
    value = {"floats": np.arange(3.0).reshape(3, 1), "ints": np.array([1, 255], dtype=np.uint8),
             "flags": np.array([True, False]), "objects": np.array([np.float64(2.5), Path("p")], dtype=object),
             "tuple": (np.float32(1.5), Path("/x")), 7: [1.0, np.int64(2)], "numbers": numbers}
    plain = to_plain(value)
    assert plain == {"floats": [[0.0], [1.0], [2.0]], "ints": [1, 255], "flags": [True, False],
                     "objects": [2.5, "p"], "tuple": [1.5, "/x"], "7": [1.0, 2], "numbers": numbers}
    assert _types(plain) <= {dict, list, float, int, bool, str, type(None)}
    assert plain["numbers"] is not numbers      # a copy: the caller's list is never shared
