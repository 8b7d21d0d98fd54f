"""State estimation for tagloc: the walking-motion EKF and candidate selection."""
