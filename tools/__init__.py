"""The maintained tools: benchmarks, the quality breakdown, the fit fingerprints, the demo data and the USD checks.

Each is a script (``python tools/<name>.py --help``) that imports its siblings by name from its own folder.
Those that import no sibling (``error_breakdown``, ``bench_common``) are also importable from the repository
root as ``tools.<name>``: ``research/`` reuses their measures and tables that way.
"""
