"""calib_core: robot kinematic calibration as a pure numeric library (numpy, scipy)."""
