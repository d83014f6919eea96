"""Robot archery on a Zenoh mesh: a simulated iCub learns to hit a target's centre with bow and
arrow (Kormushev et al. 2010). The one import name of the distribution: the contract
(`archery.protocol`), the runtime (`archery.mesh`), the five services (`archery.services`), the
simulation (`archery.sim`) and the programs (`archery.apps`, the `archery` command)."""
