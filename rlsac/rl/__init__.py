"""The learned samplers: RLSAC's environment (env and its parts), policy, kernels, rollout, episodes and
SAC agent, NG-RANSAC's network, and the checkpoint format they share.
"""
