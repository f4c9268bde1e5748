"""Built-in robots: ``floating`` (no arm: everything reachable) and ``panda`` (the Franka Panda of
``pybullet_data`` with a wrist camera; pybullet's inverse kinematics, checked by forward kinematics and
against the shelf's boards). docs/explanation/robots.md."""
