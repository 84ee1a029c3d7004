"""The live path: what a stream renders from as it runs, composed by the engine through ``timebase``.

``clock`` (pure time algebra: stream and scene clocks, what is renderable, where tau comes from),
``timebase`` (the engine's one seam: tau(t) and what stands at it), ``anchors`` (online anchors past the
checkpoint's span: store, predictor, fit thread), ``transitions`` (which transition moves them),
``config`` (their defaults, in one place), ``playback`` (the head's clock without a sensor), ``signal``
(the ingest thread waking live streams, and when batches arrived).
"""
