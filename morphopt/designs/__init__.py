"""The built-in design families, shipped with the package: one module per family (see README.md
here). morphopt.families loads them by name from this folder, after a ./designs/ folder of the
working directory; they are not meant to be imported as morphopt.designs.<name>."""
