"""Following the vehicle: the constant-velocity Kalman filter with its gate and smoother
(``kalman``), the localizer that steps a retriever, a measurer and the filter one query at a time
(``localizer``), the named methods that compose it (``methods``), and the query loop (``runs``).

Imports: ``visloc.store`` (a loaded database) and every stage below it.
"""
