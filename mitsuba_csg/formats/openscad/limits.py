"""How much of an OpenSCAD file the reader accepts: checked before the work, each named in its
message (docs/limits.md)."""

MAX_FILE_BYTES = 256 * 2 ** 20     # refuse larger files before reading them
MAX_DEPTH = 10_000                 # nesting of statements
MAX_VALUE_DEPTH = 64               # nesting of vectors inside one argument value
MAX_STATEMENTS = 10_000_000        # statements in one file
