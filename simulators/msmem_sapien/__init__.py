"""SAPIEN 3 backend (optional extra ``msmem[sapien]``)."""
