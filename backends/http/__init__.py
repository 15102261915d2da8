"""The HTTP status page and Prometheus metrics backend (``run --http [HOST:]PORT``):
:class:`backends.http.backend.HttpBackend`.  Nothing is imported here, so that loading the
``--http`` flag (:mod:`backends.http.flags`) imports neither the backend nor
prometheus-client."""
