"""People and learners: the command line, pictures, animation, Gymnasium / PettingZoo environments.
"""
