"""HTTP and websocket routes of the service, one module each."""
