"""svolsdf.mvs"""
