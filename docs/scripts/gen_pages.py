"""Build-time pages (mkdocs-gen-files): the benchmark result files and the example figures."""
