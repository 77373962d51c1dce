"""The scenario schema (validated TOML), its builders (a Setup: all a run needs), file loading and the format's
documentation.
"""
