"""``visloc bench``: the paper's brute-force path against the fast path, in one run; ``synthetic`` builds a large database to test scale."""
