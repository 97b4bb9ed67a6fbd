"""Build helpers of the repository (the docs generators); not part of the installed package."""
