"""Model selection: the regularization sweep with episode- and controller-grouped folds,
the lifting search, the twin's transfer probes, and the dask runner they share.
"""
