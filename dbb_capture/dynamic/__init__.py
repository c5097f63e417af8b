"""The dynamic-object training stage: a viewpoint-conditioned recurrent state-space model (RSSM)
that predicts an object's next RGBA frame from where the viewer stands.

Modules, in the order data flows: ``config`` (settings, presets), ``data`` (a preprocess dataset's
sequence windows), ``views`` and ``rgba`` (how views and frames are encoded), ``networks`` (encoder,
decoder, cells), ``model`` (the RSSM and its latent step), ``losses``, ``train``, ``stepper`` (the
run-time TorchScript stepper), ``evaluate`` and ``figures`` (the report), ``record`` (run.json) and
``run`` (a run folder end to end).
"""
