"""One module per faceplan sub-command: `add_arguments(parser)` and `run(args)`."""
