"""The pieces the sequencer is made of: each a small object with its own tests.

`labrunner.sequencer.CampaignRunner` only sequences; soak judgement, monitor averaging,
interlocks, the fault policy and the safe stop live here.
"""
