"""Registers the built-in methods through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_methods(register):
    register("copy-last", "methods.copy_last:CopyLast", "the t=0 sweep as every future sweep (static world)")
