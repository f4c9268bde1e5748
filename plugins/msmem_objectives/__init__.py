"""Built-in objective terms (paper: OIG, Delta H, CDC)."""
