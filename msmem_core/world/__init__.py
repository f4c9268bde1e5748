"""The simulated world every backend and skill agrees on: scenes, grid, geometry, camera, gripper,
viewpoints, scene generation and exact ground-truth voxelisation."""
