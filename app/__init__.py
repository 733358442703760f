"""App layer: the command line, renderers, camera and overlays that read the engine's state."""

# Exit codes of every command: done, the run failed (every step rejected), bad input
# (one `error:` line), interrupted (Ctrl-C or SIGTERM; complete files kept), the reader
# of stdout went away (`| head`; 128 + SIGPIPE, as a shell reports a tool killed by it).
EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 0, 1, 2, 130, 141
