"""thetahat: modular state, perturbation and parameter estimation (Grip, Saberi & Johansen)."""
