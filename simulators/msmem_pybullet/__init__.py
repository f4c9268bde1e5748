"""PyBullet backend of the msmem ``Simulator`` interface (CPU physics, TinyRenderer depth and labels)."""
