"""Inversion: signature databases, classifier, refiners and MCMC for PPR."""
