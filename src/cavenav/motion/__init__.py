"""How the vehicle moves: the admissible actions and their text (`actions`), the pose
update of SPEC section 5 (`kinematics`) and what a move costs a BlueROV2's battery
(`energy`). Pilots, the simulator and the vehicle bridge all speak it; it knows only
`cavenav.core`."""
