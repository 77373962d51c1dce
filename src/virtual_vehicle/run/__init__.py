"""Running a built scenario: the tick, the runner, checkpoints, results, task reports, tables and files.
"""
