"""Running episodes: the runner, metrics, the benchmark, executors and run-folder reports."""
