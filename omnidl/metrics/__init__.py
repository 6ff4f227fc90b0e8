"""omnidl.metrics"""
