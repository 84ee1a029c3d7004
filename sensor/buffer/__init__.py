"""Buffering: the event ring, the anchor store and the ingest thread that fills them."""
