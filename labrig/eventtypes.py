"""The one event array layout shared by the camera codecs, the simulator and recordings.

Fields: x, y (sensor pixels), p (1 ON, 0 OFF), t (int64 microseconds; which clock
depends on the producer and is stated where the array is returned).
"""

import numpy as np

EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
