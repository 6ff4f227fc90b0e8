"""omnidl.losses"""
