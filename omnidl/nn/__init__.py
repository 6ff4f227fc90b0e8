"""omnidl.nn"""
