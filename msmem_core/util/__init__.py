"""Small helpers with no msmem dependencies: atomic writes, progress bars, allocator tuning, quiet imports."""
