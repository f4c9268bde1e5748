"""Speed benchmarks (`msmem perf ...`): IG sweep, one full MSAS decision. (`msmem perf push` is registered by
the push plugin, with its own module.)"""
