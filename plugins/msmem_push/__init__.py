"""Push skill (UPS) and its analytic effect model (sigma_p)."""
