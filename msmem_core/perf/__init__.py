"""Speed benchmarks (`msmem perf ...`): IG sweep, push prediction, one full MSAS decision."""
