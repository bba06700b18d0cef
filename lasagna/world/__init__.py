"""lasagna.world"""
