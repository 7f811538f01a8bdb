"""Worker processes: the only place where the engine runs for the service.

``tasks`` is what runs inside a worker (it imports only ``core``, so workers stay lean);
``pool`` is the parent side.
"""
