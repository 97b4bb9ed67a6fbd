"""The carriers: UDP (with its kernel socket filter) and Zenoh (with its fleet's liveliness), behind
the one small interface the session loop needs (``base.Transport``).  Nothing here runs a session:
the process around an endpoint is ``shell/``, the checker ``conformance/``."""
