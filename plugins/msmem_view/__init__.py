"""The viewpoint skill: move the camera to one of the candidate viewpoints and observe."""
