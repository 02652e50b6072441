"""usmswitch.sim"""
