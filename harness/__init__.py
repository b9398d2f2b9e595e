"""The Python side of mbfg: reference generators, comparisons and reports."""
