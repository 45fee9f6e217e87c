"""Online learning of the RHONN weights (EKF, paper eq. 11-12)."""
