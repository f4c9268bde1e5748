"""Shared machinery for plugins that learn: sharded data generation and training loops."""
