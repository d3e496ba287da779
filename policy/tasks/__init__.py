"""What a controller is asked to do and how it is scored: episodes, scenarios, arm envelopes.

Shared by reinforcement learning (`policy.rl`) and the campaigns (`policy.campaigns`), so it sits
below both.
"""
