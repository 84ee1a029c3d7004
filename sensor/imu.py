"""IMU samples as the sensor layer holds them: a structured array, accelerometer in g and gyroscope in
degrees per second (dv's units), in the camera's axes."""

import numpy as np

IMU_DTYPE = np.dtype([("t", "<i8"), ("accel", "<f4", (3,)), ("gyro", "<f4", (3,)), ("temperature", "<f4")])
"""t int64 µs on the stream clock, accel float32 [3] g, gyro float32 [3] degrees/s, temperature °C."""
