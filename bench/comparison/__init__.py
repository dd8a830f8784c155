"""The equal-wall-clock model comparison as a committed, resumable plan (`nemsim bench compare`).

The comparison (NEMSim, its ablations and five baselines, each trained for the same wall time on one core,
after short probes that pick each baseline's size and learning rate) costs more core-hours than a working
session has, and a session may start on a fresh machine where runs/ and data/ are gone. So the protocol is
a file in the repository, and so is its outcome: ``plan`` reads the plan and says where every run stands,
reading each run's directory and a committed record of the finished runs (their summary, metrics and
config, a few KB each); ``runner`` runs what is left as ``nemsim train`` subprocesses, one core each, and
copies every finished run into the record. Any session continues with the same command.
"""
