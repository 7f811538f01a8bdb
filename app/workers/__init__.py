"""The processes that run the engine for the service: the task table (``tasks``), the pool of
worker processes (``pool``), their set-up (``process``) and what their failures answer
(``failures``), shared by both jobs backends."""
