"""Engine-independent helpers for simulator backends (the floating gripper's motion)."""
