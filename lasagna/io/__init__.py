"""lasagna.io"""
