"""dbb-batch: many captures through preprocess -> train -> bundle -> verify on Ray (docs/batch.md).

Modules: ``config`` (the settings of a batch), ``captures`` (which folders are captures, their
kind, where their outputs go), ``records`` (typed results and ``summary.json``), ``stages`` (one
stage of one capture, as a worker runs it; no Ray), ``cluster`` (joining or starting Ray, the
shared-filesystem check, resource requests), ``table`` (the live and final tables), ``run`` (the
driver: stages chained per capture, retries, resumption).
"""
