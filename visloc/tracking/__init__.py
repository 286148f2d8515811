"""Following the vehicle: the constant-velocity Kalman filter with its gate and smoother
(``kalman``), the localizer that steps a retriever, a measurer and the filter one query at a time
(``localizer``), the named methods that compose it (``methods``), the query loop (``runs``), a track that follows
map points between full localizations (``follower``) and the views it may use as it goes (``viewwindow``).

Imports: ``visloc.store`` (a loaded database) and every stage below it.
"""
