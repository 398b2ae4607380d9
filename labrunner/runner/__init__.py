"""The pieces the sequencer is made of: each a small object with its own tests.

`labrunner.sequencer.CampaignRunner` only sequences. What it judges or keeps on the way lives
here: the soak window and timeout verdict (`soak`), the monitor means (`monitor`), the
interlocks (`interlocks`), the fault policy and auto-resume (`fault_policy`), the drivers'
retry and link events (`fault_log`), requests and heartbeat (`control`), the preflight checks
(`preflight`) and the one safe stop (`safe_stop`), which `labrunner abort` uses too.
"""
