"""The ``iwsim`` subcommands, one module per group: each ``register(sub)`` adds its
parsers to the command line's and sets the handler each one runs (``args.func``).

A module imports at its top only what building the parser needs (no torch: ``iwsim
--help`` stays quick); a handler imports the library it calls when it runs.
"""
