"""gscan's version, one place: the package, the CLI's --version, the service's OpenAPI page and the wheel."""
__version__ = "0.2.0"
