"""The equal-wall-clock model comparison as a committed, resumable plan (`nemsim bench compare`).

The comparison (NEMSim, its ablations and five baselines, each trained for the same wall time on one core,
after short probes that pick each baseline's size and learning rate) costs more core-hours than one sitting,
and a fresh machine has no runs/ or data/. So the protocol is a file in the repository, and so is its
outcome: ``plan`` reads the plan and says where every run stands, from each run's directory and a committed
record of the finished runs (summary, metrics and config, a few KB each); ``runner`` runs what is left as
``nemsim train`` subprocesses, one core each, and copies every finished run into the record. The same
command continues it anywhere.
"""
