"""The process shell: what runs one sans-I/O endpoint (``teleop.session.endpoint``) as an OS process.
Its 1 kHz loop on the monotonic clock (``realtime``, ``runner``), a process's options and console
lines, and its records (MCAP logs, ROLE.json, the live view).  It reads clocks, sockets (through
``transport/``) and files so that the core never does; it uses only the core's public names."""
