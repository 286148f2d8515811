"""``visloc bench``: the paper's brute-force path against the fast path, in one run (issue 5)."""
