"""Stage 4, deviation models: OLS RBF network, thin-plate spline, the physical model, model selection and training."""
