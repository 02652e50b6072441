"""usmswitch.predictor"""
