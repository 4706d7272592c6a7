"""The data path's logic, one stage a module (issue #34), each importing none of the others: `frames`, the
capture's side (two images -> a Frame, the shard plan, the workers' membership (Roster), the dynamic window);
`shards`, the worker's (a Frame and a k-range -> a Correlation); `gather`, the reducer's (the shards -> a
complete profile -> the decision, the profile and the command). The processes around them: services/pipeline/."""
