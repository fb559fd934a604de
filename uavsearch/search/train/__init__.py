"""Training: stage 1 (perception), stage 2 (fusion + policy, REINFORCE) and the reactive policy; never imports evaluate."""
