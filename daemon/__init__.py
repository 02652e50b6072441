"""usmswitch.daemon"""
