"""The long-running RSU service and the `rsucal` command line: everything with a socket, a thread, a clock or
an open file. Imports point one way: daemon -> pipeline -> schemas."""

__version__ = "0.1.0"
