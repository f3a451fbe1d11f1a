"""After the renderer: optimisation, gradient images, the paper's experiments, and the
plots and JSON they write."""
